"""Strict fake of ``quanser.hardware`` (HIL, HILError, PWMMode, MAX_STRING_LENGTH) for tests."""

import time

import numpy as np

from quanser import _fake
from quanser._fake import STATE

MAX_STRING_LENGTH = 2048


class HILError(Exception):
    """As Quanser's: ``error_code`` and ``get_error_message()``; ``str(e)`` is the code."""

    def __init__(self, error_code, detail=""):
        Exception.__init__(self, str(error_code))
        self.error_code = error_code
        self.detail = detail

    def get_error_message(self):
        text = _fake.MESSAGES.get(self.error_code, "HIL error")
        return text + (": " + self.detail if self.detail else "")


class PWMMode(object):
    DUTY_CYCLE = 0
    FREQUENCY = 1
    TIME = 2


class Clock(object):
    HARDWARE_CLOCK_0 = 0


def _channels(channels, n, allowed, what):
    """Channels as the real API takes them: a 4-byte integer NumPy array of exactly n entries,
    each one the board has; n == 0 goes with None."""
    if n == 0:
        if channels is not None and len(channels) != 0:
            raise HILError(_fake.INVALID_ARGUMENT, "{}: 0 channels but a channel array".format(what))
        return []
    if not isinstance(channels, np.ndarray) or channels.dtype.kind not in "iu" or channels.dtype.itemsize != 4:
        raise HILError(_fake.INVALID_ARGUMENT, "{}: channels must be a 32-bit integer array, got {!r}".format(
            what, type(channels).__name__ if not isinstance(channels, np.ndarray) else channels.dtype))
    if channels.ndim != 1 or channels.size != n:
        raise HILError(_fake.INVALID_ARGUMENT, "{}: {} channels given, n = {}".format(what, channels.size, n))
    chans = [int(c) for c in channels]
    bad = [c for c in chans if c not in allowed]
    if bad:
        raise HILError(_fake.INVALID_CHANNEL, "{}: {} not on board '{}' (has {})".format(
            what, bad, STATE.board["name"], sorted(allowed)))
    if len(set(chans)) != len(chans):
        raise HILError(_fake.INVALID_ARGUMENT, "{}: repeated channels {}".format(what, chans))
    return chans


def _buffer(buf, n, kinds, itemsize, what):
    if n == 0:
        if buf is not None and len(buf) != 0:
            raise HILError(_fake.INVALID_BUFFER, "{}: a buffer for 0 channels".format(what))
        return
    if not isinstance(buf, np.ndarray) or buf.dtype.kind not in kinds or buf.dtype.itemsize != itemsize:
        raise HILError(_fake.INVALID_BUFFER, "{}: buffer must be a {}-byte {} array, got {}".format(
            what, itemsize, kinds, getattr(buf, "dtype", type(buf).__name__)))
    if buf.size != n or not buf.flags["C_CONTIGUOUS"]:
        raise HILError(_fake.INVALID_BUFFER, "{}: buffer of {} values for {} channels".format(what, buf.size, n))


class HIL(object):
    """One handle on the (single) physical board of the configured car."""

    INFINITE = -1

    def __init__(self, card_type=None, card_identifier="0"):
        self._open = False
        self._closed = False
        if card_type is not None:
            self.open(card_type, card_identifier)

    # --- life cycle -------------------------------------------------------------------------
    def open(self, card_type, card_identifier):
        if self._open:
            raise HILError(_fake.INVALID_ARGUMENT, "the card is already open")
        if card_type != STATE.board["name"]:
            STATE.event("open_refused", board=card_type)
            raise HILError(_fake.BOARD_NOT_FOUND, "no '{}' board here".format(card_type))
        if str(card_identifier) != "0":
            raise HILError(_fake.BOARD_NOT_FOUND, "no board with identifier {!r}".format(card_identifier))
        with STATE.lock:
            self._open = True
            STATE.open_handles += 1
        STATE.event("open", board=card_type)

    def is_valid(self):
        return self._open

    def close(self):
        if not self._open:
            return
        with STATE.lock:
            self._open = False
            self._closed = True
            STATE.open_handles -= 1
            if STATE.open_handles == 0:
                STATE.latched = False  # the manual: close and reopen the card to clear the latch
        STATE.event("close")

    def _need_open(self, what):
        if not self._open:
            raise HILError(_fake.NOT_OPEN, what)
        STATE.expire_watchdog_if_due()

    # --- configuration --------------------------------------------------------------------------
    def set_card_specific_options(self, options, max_length):
        self._need_open("set_card_specific_options")
        if not isinstance(options, str) or not isinstance(max_length, int) or len(options) > max_length:
            raise HILError(_fake.INVALID_ARGUMENT, "options must be a string shorter than max_length")
        parsed = {}
        for item in options.split(";"):
            if not item:
                continue
            key, sep, value = item.partition("=")
            if not sep or key not in ("steer_bias", "motor_limit"):
                raise HILError(_fake.INVALID_ARGUMENT, "unknown card option {!r}".format(item))
            parsed[key] = float(value)
        if "motor_limit" in parsed and not 0.0 < parsed["motor_limit"] <= 1.0:
            raise HILError(_fake.INVALID_ARGUMENT, "motor_limit must be in (0, 1]")
        STATE.event("options", options=parsed)

    def set_pwm_mode(self, channels, n, modes):
        self._need_open("set_pwm_mode")
        chans = _channels(channels, n, STATE.board["pwm_out"], "set_pwm_mode")
        _buffer(modes, n, "iu", 4, "set_pwm_mode")
        if any(int(m) not in (PWMMode.DUTY_CYCLE, PWMMode.FREQUENCY, PWMMode.TIME) for m in modes):
            raise HILError(_fake.INVALID_ARGUMENT, "unknown PWM mode")
        STATE.event("pwm_mode", channels=chans, modes=[int(m) for m in modes])

    def set_pwm_frequency(self, channels, n, frequencies):
        self._need_open("set_pwm_frequency")
        chans = _channels(channels, n, STATE.board["pwm_out"], "set_pwm_frequency")
        _buffer(frequencies, n, "f", 8, "set_pwm_frequency")
        STATE.event("pwm_frequency", channels=chans, hz=[float(f) for f in frequencies])

    def set_encoder_quadrature_mode(self, channels, n, modes):
        self._need_open("set_encoder_quadrature_mode")
        chans = _channels(channels, n, set(STATE.board["encoder_in"]), "set_encoder_quadrature_mode")
        _buffer(modes, n, "iu", 4, "set_encoder_quadrature_mode")
        if any(int(m) not in (0, 1, 2, 4) for m in modes):
            raise HILError(_fake.INVALID_ARGUMENT, "quadrature mode must be 0, 1, 2 or 4")
        STATE.event("quadrature", channels=chans, modes=[int(m) for m in modes])

    def set_encoder_filter_frequency(self, channels, n, frequencies):
        self._need_open("set_encoder_filter_frequency")
        chans = _channels(channels, n, set(STATE.board["encoder_in"]), "set_encoder_filter_frequency")
        _buffer(frequencies, n, "f", 8, "set_encoder_filter_frequency")
        STATE.event("encoder_filter", channels=chans, hz=[float(f) for f in frequencies])

    def set_encoder_counts(self, channels, n, counts):
        self._need_open("set_encoder_counts")
        chans = _channels(channels, n, set(STATE.board["encoder_in"]), "set_encoder_counts")
        _buffer(counts, n, "i", 4, "set_encoder_counts")
        STATE.event("encoder_counts", channels=chans, counts=[int(c) for c in counts])

    # --- I/O ------------------------------------------------------------------------------------
    def _check_writable(self, path):
        wd = STATE.watchdog
        if wd is not None and wd["expired"]:
            raise HILError(_fake.WATCHDOG_EXPIRED, "clear the watchdog before writing")
        if STATE.latched and (path == "write" or STATE.fail_all_paths):
            raise HILError(_fake.OVER_CURRENT, path)

    def _apply(self, kind, chans, values):
        with STATE.lock:
            for c, v in zip(chans, values):
                STATE.outputs[(kind, c)] = float(v)

    def write(self, a_ch, n_a, p_ch, n_p, d_ch, n_d, o_ch, n_o, a_buf, p_buf, d_buf, o_buf):
        self._need_open("write")
        board = STATE.board
        _channels(a_ch, n_a, set(), "write analog")  # neither QCar has analog outputs
        pwm = _channels(p_ch, n_p, board["pwm_out"], "write pwm")
        dig = _channels(d_ch, n_d, board["digital_out"], "write digital")
        oth = _channels(o_ch, n_o, board["other_out"], "write other")
        _buffer(a_buf, n_a, "f", 8, "write analog")
        _buffer(p_buf, n_p, "f", 8, "write pwm")
        _buffer(d_buf, n_d, "iub", 1, "write digital")
        _buffer(o_buf, n_o, "f", 8, "write other")
        if p_buf is not None and n_p and np.any(np.abs(p_buf) > 1.0):
            raise HILError(_fake.INVALID_ARGUMENT, "PWM duty cycle outside [-1, 1]")
        with STATE.lock:
            self._check_writable("write")
            if STATE.fail_write_after is not None and STATE.writes >= STATE.fail_write_after:
                STATE.latched = True
                STATE.fail_write_after = None  # one over-current event
                STATE.event("write_failed", reason="over-current")
                raise HILError(_fake.OVER_CURRENT, "write")
            STATE.writes += 1
            self._apply("pwm", pwm, p_buf if n_p else [])
            self._apply("digital", dig, d_buf if n_d else [])
            self._apply("other", oth, o_buf if n_o else [])
        STATE.event("write", pwm=dict(zip(pwm, _floats(p_buf, n_p))), digital=dict(zip(dig, _floats(d_buf, n_d))),
                    other=dict(zip(oth, _floats(o_buf, n_o))))

    def write_pwm(self, channels, n, buf):
        self._need_open("write_pwm")
        chans = _channels(channels, n, STATE.board["pwm_out"], "write_pwm")
        _buffer(buf, n, "f", 8, "write_pwm")
        with STATE.lock:
            self._check_writable("write_pwm")
            self._apply("pwm", chans, buf)
        STATE.event("write_pwm", pwm=dict(zip(chans, _floats(buf, n))))

    def write_other(self, channels, n, buf):
        self._need_open("write_other")
        chans = _channels(channels, n, STATE.board["other_out"], "write_other")
        _buffer(buf, n, "f", 8, "write_other")
        with STATE.lock:
            self._check_writable("write_other")
            self._apply("other", chans, buf)
        STATE.event("write_other", other=dict(zip(chans, _floats(buf, n))))

    def write_digital(self, channels, n, buf):
        self._need_open("write_digital")
        chans = _channels(channels, n, STATE.board["digital_out"], "write_digital")
        _buffer(buf, n, "iub", 1, "write_digital")
        with STATE.lock:
            self._check_writable("write_digital")
            self._apply("digital", chans, buf)
        STATE.event("write_digital", digital=dict(zip(chans, _floats(buf, n))))

    def read(self, a_ch, n_a, e_ch, n_e, d_ch, n_d, o_ch, n_o, a_buf, e_buf, d_buf, o_buf):
        self._need_open("read")
        board = STATE.board
        ana = _channels(a_ch, n_a, set(board["analog_in"]), "read analog")
        enc = _channels(e_ch, n_e, set(board["encoder_in"]), "read encoder")
        _channels(d_ch, n_d, set(), "read digital")
        oth = _channels(o_ch, n_o, set(board["other_in"]), "read other")
        _buffer(a_buf, n_a, "f", 8, "read analog")
        _buffer(e_buf, n_e, "i", 4, "read encoder")
        _buffer(o_buf, n_o, "f", 8, "read other")
        for i, c in enumerate(ana):
            a_buf[i] = board["analog_in"][c]
        for i, c in enumerate(enc):
            e_buf[i] = board["encoder_in"][c]
        for i, c in enumerate(oth):
            o_buf[i] = board["other_in"][c]

    # --- the board's watchdog -------------------------------------------------------------------
    def _need_watchdog(self, what):
        self._need_open(what)
        if not STATE.watchdog_supported:
            raise HILError(_fake.NOT_SUPPORTED, what)

    def _expiration(self, kind, channels, n, buf, allowed, what):
        self._need_watchdog(what)
        chans = _channels(channels, n, allowed, what)
        _buffer(buf, n, "f", 8, what)
        with STATE.lock:
            pending = STATE.__dict__.setdefault("expiration_states", {})
            for c, v in zip(chans, buf):
                pending[(kind, c)] = float(v)
        STATE.event("expiration_state", kind=kind, channels=chans, values=_floats(buf, n))

    def watchdog_set_pwm_expiration_state(self, channels, n, buf):
        self._expiration("pwm", channels, n, buf, STATE.board["pwm_out"], "watchdog_set_pwm_expiration_state")

    def watchdog_set_other_expiration_state(self, channels, n, buf):
        self._expiration("other", channels, n, buf, STATE.board["other_out"], "watchdog_set_other_expiration_state")

    def watchdog_start(self, timeout):
        self._need_watchdog("watchdog_start")
        if not isinstance(timeout, float) or not timeout > 0:
            raise HILError(_fake.INVALID_ARGUMENT, "timeout must be a positive float")
        with STATE.lock:
            states = dict(STATE.__dict__.get("expiration_states", {}))
            STATE.watchdog = {"timeout": timeout, "last": time.monotonic(), "states": states, "expired": False}
        STATE.event("watchdog_start", timeout=timeout, states=dict((str(k), v) for k, v in states.items()))

    def watchdog_reload(self):
        self._need_watchdog("watchdog_reload")
        with STATE.lock:
            STATE.expire_watchdog_if_due()
            wd = STATE.watchdog
            if wd is None:
                raise HILError(_fake.INVALID_ARGUMENT, "the watchdog is not running")
            if wd["expired"]:
                return False
            wd["last"] = time.monotonic()
            return True

    def watchdog_is_expired(self):
        self._need_watchdog("watchdog_is_expired")
        STATE.expire_watchdog_if_due()
        return bool(STATE.watchdog and STATE.watchdog["expired"])

    def watchdog_clear(self):
        self._need_watchdog("watchdog_clear")
        with STATE.lock:
            if STATE.watchdog is not None:
                STATE.watchdog["expired"] = False
                STATE.watchdog["last"] = time.monotonic()
        STATE.event("watchdog_clear")

    def watchdog_stop(self):
        self._need_watchdog("watchdog_stop")
        with STATE.lock:
            STATE.watchdog = None
        STATE.event("watchdog_stop")


def _floats(buf, n):
    return [] if not n else [float(v) for v in buf]
