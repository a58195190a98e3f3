"""HSV profiles: the lane line's colour range as a YAML file (``--hsv FILE``), written by the tuner
(``qcarlab lane-follow --hsv-tune``, ``qcarlab detect lanes PHOTO --hsv-tune``).

The file (all keys but ``yellow.hsv_min``/``hsv_max`` optional; OpenCV units: H 0..179 = degrees
/ 2, S and V 0..255)::

    qcarlab: hsv-profile            # what this file is
    version: 1
    yellow:                         # the lane line the lab tracks (the sheet's centre line)
      hsv_min: [17, 85, 70]         # lower bound H, S, V (inclusive)
      hsv_max: [38, 255, 255]       # upper bound H, S, V (inclusive)
      sliders:                      # the same range as the sheet's userInput sliders (written
        hue: {mean: 27.5, window: 21}       # for reading; min = mean - window / 2,
        saturation: {mean: 170, window: 170}  # max = mean + window / 2); used only when
        value: {mean: 162.5, window: 185}     # hsv_min / hsv_max are absent
    white:                          # the white line finder (qcarlab.perception.lane.white_from_hsv)
      s_max: 80                     # saturation at most
      v_min: 110                    # value at least (and 0.8 x the frame's brightest floor)
    tuned_on: [photo.jpg]           # what the tuner saw (information)
    score: 0.93                     # the tuner's line-fit quality (information)

A wrong file is one line naming the file and the key (exit 2).
"""

from __future__ import annotations

from pathlib import Path

from qcarlab.errors import InputError
from qcarlab.perception.hsv_range import CHANNELS, HsvProfile
from qcarlab.perception.lane import WHITE_S_MAX, WHITE_V_MIN
from qcarlab.perception.stop_sign import check_hsv
from qcarlab.yamlio import load_yaml

__all__ = ["HsvProfile", "load_hsv_profile", "profile_yaml", "save_hsv_profile"]

def profile_yaml(profile: HsvProfile) -> str:
    """The profile as the YAML text of the module docstring."""
    s = profile.sliders
    lines = [
        "# qcarlab HSV profile (qcarlab lane-follow --hsv FILE, qcarlab detect lanes --hsv FILE)",
        "# OpenCV units: H 0..179 = degrees / 2, S and V 0..255; bounds inclusive",
        "qcarlab: hsv-profile",
        "version: 1",
        "yellow:",
        f"  hsv_min: [{', '.join(map(str, profile.hsv_min))}]",
        f"  hsv_max: [{', '.join(map(str, profile.hsv_max))}]",
        "  sliders:  # the sheet's userInput sliders for the same range (min = mean - window / 2)",
    ]
    for name, (mean, window) in zip(CHANNELS, s):
        lines.append(f"    {name}: {{mean: {mean:g}, window: {window}}}")
    lines += ["white:", f"  s_max: {profile.white_s_max}", f"  v_min: {profile.white_v_min}"]
    if profile.tuned_on:
        lines.append("tuned_on: [" + ", ".join(_quote(t) for t in profile.tuned_on) + "]")
    if profile.score is not None:
        lines.append(f"score: {profile.score:.3f}")
    return "\n".join(lines) + "\n"



def _quote(text: str) -> str:
    import json

    return json.dumps(str(text))


def _triple(value, where: str) -> tuple[int, int, int]:
    if not isinstance(value, (list, tuple)) or len(value) != 3:
        raise InputError(f"{where}: expected three numbers [H, S, V], got {value!r}")
    try:
        return check_hsv(value, where)
    except InputError as exc:
        raise InputError(f"{exc}") from None


def _int(value, where: str, top: int = 255) -> int:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not float(value).is_integer() \
            or not 0 <= value <= top:
        raise InputError(f"{where}: expected a whole number 0..{top}, got {value!r}")
    return int(value)


def load_hsv_profile(path: str | Path) -> HsvProfile:
    """Read a profile file (module docstring); one-line InputError naming the file and key."""
    p = Path(path)
    doc = load_yaml(p, "HSV profile")
    if not isinstance(doc, dict):
        raise InputError(f"{p}: an HSV profile is a YAML mapping with a 'yellow' section")
    kind = doc.get("qcarlab", "hsv-profile")
    if kind != "hsv-profile":
        raise InputError(f"{p}: this is a qcarlab {kind!r} file, not an hsv-profile")
    yellow = doc.get("yellow")
    if not isinstance(yellow, dict):
        raise InputError(f"{p}: missing 'yellow' section (hsv_min and hsv_max)")
    white = doc.get("white") or {}
    if not isinstance(white, dict):
        raise InputError(f"{p}: 'white' must be a mapping (s_max, v_min)")
    kw = {
        "white_s_max": _int(white.get("s_max", WHITE_S_MAX), f"{p}: white.s_max"),
        "white_v_min": _int(white.get("v_min", WHITE_V_MIN), f"{p}: white.v_min"),
        "tuned_on": tuple(str(t) for t in (doc.get("tuned_on") or ())),
        "score": float(doc["score"]) if isinstance(doc.get("score"), (int, float)) else None,
    }
    try:
        if "hsv_min" in yellow or "hsv_max" in yellow:
            return HsvProfile(_triple(yellow.get("hsv_min"), f"{p}: yellow.hsv_min"),
                              _triple(yellow.get("hsv_max"), f"{p}: yellow.hsv_max"), **kw)
        sl = yellow.get("sliders")
        if not isinstance(sl, dict) or any(not isinstance(sl.get(c), dict) for c in CHANNELS):
            raise InputError(f"{p}: yellow needs hsv_min and hsv_max (or sliders: hue, saturation, value)")
        pairs = []
        for c in CHANNELS:
            mean, window = sl[c].get("mean"), sl[c].get("window")
            if not all(isinstance(x, (int, float)) and not isinstance(x, bool) for x in (mean, window)):
                raise InputError(f"{p}: yellow.sliders.{c}: expected mean and window numbers")
            pairs.append((float(mean), float(window)))
        return HsvProfile.from_sliders(pairs, **kw)
    except InputError as exc:
        msg = str(exc)
        raise InputError(msg if msg.startswith(str(p)) else f"{p}: {msg}") from None


def save_hsv_profile(profile: HsvProfile, path: str | Path) -> Path:
    """Write ``profile`` to ``path`` (folders made as needed); the path written."""
    p = Path(path)
    try:
        p.parent.mkdir(parents=True, exist_ok=True)
        p.write_text(profile_yaml(profile), encoding="utf-8")
    except OSError as exc:
        raise InputError(f"{p}: cannot write the HSV profile ({exc.strerror or exc})") from None
    return p
