"""The QCar's lamps: names, the sheet's HIL channels (11000-11011), and parsing of lamp lists.

The car has 8 lamps and 4 user LEDs. Their state is a tuple of 12 intensities in [0, 1], in the
order of the lab sheet's HIL-Write "other" channels (Figure 19)::

    11000 brake              11004-11007 user0..user3     11008 indicator_rear_left
    11001 reverse                                         11009 indicator_rear_right
    11002 headlamp_left                                   11010 indicator_front_left
    11003 headlamp_right                                  11011 indicator_front_right

Users name lamps one by one or by group: ``brake``, ``reverse``, ``headlamps``, ``indicators``
(all four), ``left-indicators``, ``right-indicators``, ``hazard`` (all four indicators), ``user``
(the four user LEDs), ``user0``..``user3``, ``all``.
"""

from __future__ import annotations

import functools

from collections.abc import Iterable, Mapping

from qcarlab.errors import InputError

LAMP_NAMES: tuple[str, ...] = (
    "brake",
    "reverse",
    "headlamp_left",
    "headlamp_right",
    "user0",
    "user1",
    "user2",
    "user3",
    "indicator_rear_left",
    "indicator_rear_right",
    "indicator_front_left",
    "indicator_front_right",
)
HIL_CHANNELS: dict[str, int] = {name: 11000 + i for i, name in enumerate(LAMP_NAMES)}
N_LAMPS = len(LAMP_NAMES)
ALL_OFF: tuple[float, ...] = (0.0,) * N_LAMPS

_LEFT = ("indicator_rear_left", "indicator_front_left")
_RIGHT = ("indicator_rear_right", "indicator_front_right")
LAMP_GROUPS: dict[str, tuple[str, ...]] = {
    "headlamps": ("headlamp_left", "headlamp_right"),
    "indicators": _LEFT + _RIGHT,
    "hazard": _LEFT + _RIGHT,
    "left-indicators": _LEFT,
    "right-indicators": _RIGHT,
    "user": ("user0", "user1", "user2", "user3"),
    "all": LAMP_NAMES,
}


def known_lamp_words() -> list[str]:
    """Every name ``parse_lamps`` accepts, groups first."""
    return list(LAMP_GROUPS) + [n.replace("_", "-") for n in LAMP_NAMES]


def _expand(word: str) -> tuple[str, ...]:
    key = word.strip().lower()
    if key in LAMP_GROUPS:
        return LAMP_GROUPS[key]
    key = key.replace("-", "_")
    if key in HIL_CHANNELS:
        return (key,)
    raise InputError(f"unknown lamp '{word.strip()}' (choose from: {', '.join(known_lamp_words())})")


@functools.lru_cache(maxsize=256)
def lamps_named(names: tuple[str, ...]) -> tuple[float, ...]:
    """``parse_lamps`` for a tuple of lamp names, cached: what a lab's ``indicator_and_lamps``
    block returns, turned into the 12 intensities every tick at no cost."""
    return parse_lamps(list(names)) if names else ALL_OFF


def parse_lamps(spec: str | Iterable[str] | Mapping[str, float] | None) -> tuple[float, ...]:
    """Turn ``"brake,headlamps"``, ``["brake"]``, ``{"brake": 0.5}`` or a 12-tuple into intensities.

    Intensities are fractions in [0, 1] (the sheet's % divided by 100); names switch lamps fully on.
    """
    if spec is None:
        return ALL_OFF
    if isinstance(spec, str):
        words = [w for w in spec.split(",") if w.strip()]
        if spec.strip().lower() in ("", "none", "off"):
            return ALL_OFF
        return parse_lamps(words)
    if isinstance(spec, Mapping):
        state = list(ALL_OFF)
        for word, level in spec.items():
            level = float(level)
            if not 0.0 <= level <= 1.0:
                raise InputError(f"lamp '{word}': intensity must be in [0, 1], got {level}")
            for name in _expand(word):
                state[LAMP_NAMES.index(name)] = level
        return tuple(state)
    items = list(spec)
    if len(items) == N_LAMPS and all(isinstance(v, (int, float)) for v in items):
        values = tuple(float(v) for v in items)
        if not all(0.0 <= v <= 1.0 for v in values):
            raise InputError("lamp intensities must be in [0, 1]")
        return values
    state = list(ALL_OFF)
    for word in items:
        if not isinstance(word, str):
            raise InputError(f"lamp names must be strings, got {word!r}")
        for name in _expand(word):
            state[LAMP_NAMES.index(name)] = 1.0
    return tuple(state)


def lamps_on(state: Iterable[float]) -> list[str]:
    """Names of the lamps whose intensity is above zero, in channel order."""
    return [name for name, level in zip(LAMP_NAMES, state) if level > 0.0]
