"""What each GUI control of the viewer accepts, as data, and the one check every value a browser sends goes through.

A browser tab can send any value for any control (the websocket carries msgpack, not what the widget allows), and
viser stores a value and re-broadcasts it to every later tab before any callback of ours runs: one ``1e30`` for an
integer control made every later connection fail (msgpack cannot encode the int) and a layer name that does not
exist made every frame fail. ``app.py`` therefore calls ``ControlTable.validate`` on each incoming value BEFORE
viser sees it; a value it refuses never reaches viser's state, the control keeps its last good value and the panel
says why. The GUI is built from the same table (ranges and options are stated once).
"""

from __future__ import annotations

import math
import numbers
from dataclasses import dataclass


class Refused(ValueError):
    """A control value the server does not take. ``reason`` completes ``"<name>: <value> ..."``."""

    def __init__(self, name: str, value, reason: str):
        self.name, self.value, self.reason = name, value, reason
        super().__init__(f"{name}: {shown(value)} {reason}")

    def message(self, kept=None, has_kept: bool = True) -> str:
        """What the panel shows: ``Max spp: 1e+30 is out of range 1..4096, kept 64``."""
        return f"{self}, kept {shown(kept)}" if has_kept else str(self)


def shown(value, limit: int = 40) -> str:
    """A value as the panel shows it: short (a long string or list is cut) and without backticks (the panel is
    markdown; the caller puts it in a code span)."""
    if isinstance(value, float):
        text = format(value, ".6g")
    elif isinstance(value, tuple) and all(isinstance(v, float) for v in value):
        text = "(" + ", ".join(format(v, ".6g") for v in value) + ")"
    else:
        text = repr(value)
    text = text.replace("`", "'").replace("\n", " ")
    return text if len(text) <= limit else text[:limit - 1] + "…"


@dataclass(frozen=True)
class Control:
    """What one control accepts."""

    kind: str  # "number" | "vector" | "choice" | "text" | "checkbox" | "button" | "pose"
    lo: float = -math.inf  # number / vector: smallest value of each component (inclusive)
    hi: float = math.inf  # number / vector: largest value of each component (inclusive); pose: largest |position|
    integer: bool = False  # number / vector: whole numbers only (the value becomes an int)
    size: int = 1  # vector: number of components
    options: tuple[str, ...] = ()  # choice: the values accepted
    max_chars: int = 64  # text: longest value accepted

    def __post_init__(self) -> None:
        if self.kind not in ("number", "vector", "choice", "text", "checkbox", "button", "pose"):
            raise ValueError(f"unknown control kind {self.kind!r}")
        if not self.lo <= self.hi:
            raise ValueError(f"empty range {self.lo}..{self.hi}")
        if self.kind == "choice" and not self.options:
            raise ValueError("a choice needs options")


def number(lo: float, hi: float, integer: bool = False) -> Control:
    return Control("number", lo=lo, hi=hi, integer=integer)


def vector(size: int, lo: float = -math.inf, hi: float = math.inf, integer: bool = False) -> Control:
    return Control("vector", lo=lo, hi=hi, integer=integer, size=size)


def choice(options) -> Control:
    return Control("choice", options=tuple(options))


def text(max_chars: int = 64) -> Control:
    return Control("text", max_chars=max_chars)


CHECKBOX = Control("checkbox")
BUTTON = Control("button")


def pose(reach: float) -> Control:
    """A gizmo pose (wxyz, position): a rotation quaternion (normalised here) and a position within ``reach``."""
    return Control("pose", hi=reach)


def _range(spec: Control) -> str:
    return f"{spec.lo:g}..{spec.hi:g}"


def _scalar(name: str, spec: Control, value, whole):
    """One number of a number / vector control (``whole``: the value refused, for the message)."""
    if isinstance(value, bool) or not isinstance(value, numbers.Real):
        raise Refused(name, whole, "is not a number")
    try:
        x = float(value)
    except OverflowError:  # an int beyond float
        raise Refused(name, whole, f"is out of range {_range(spec)}") from None
    if not math.isfinite(x):
        raise Refused(name, whole, "is not a finite number")
    if not spec.lo <= x <= spec.hi:
        raise Refused(name, whole, f"is out of range {_range(spec)}")
    if spec.integer:
        if x != math.floor(x):
            raise Refused(name, whole, "is not a whole number")
        return int(x)
    return x


def _sequence(name: str, value, size: int) -> tuple:
    if not isinstance(value, (list, tuple)) or len(value) != size:
        raise Refused(name, value, f"is not a list of {size} numbers")
    return tuple(value)


def check(name: str, spec: Control, value):
    """``value`` as the control holds it (int / float / tuple / str / bool), or Refused."""
    k = spec.kind
    if k == "number":
        return _scalar(name, spec, value, value)
    if k == "vector":
        return tuple(_scalar(name, spec, v, value) for v in _sequence(name, value, spec.size))
    if k == "choice":
        if not isinstance(value, str) or value not in spec.options:
            listed = ", ".join(spec.options)
            raise Refused(name, value, f"is not one of {listed if len(listed) < 120 else listed[:119] + '…'}")
        return value
    if k == "text":
        if not isinstance(value, str):
            raise Refused(name, value, "is not text")
        if len(value) > spec.max_chars:
            raise Refused(name, value, f"is longer than {spec.max_chars} characters")
        if not value.isprintable():
            raise Refused(name, value, "has control characters")
        return value
    if k == "checkbox":
        if not isinstance(value, bool):
            raise Refused(name, value, "is not true / false")
        return value
    if k == "button":
        if value is not True:
            raise Refused(name, value, "is not a click (true)")
        return True
    # pose: (wxyz, position)
    wxyz, position = _sequence(name, value, 2)
    unit = Control("vector", size=4)
    q = tuple(_scalar(name, unit, v, value) for v in _sequence(name, wxyz, 4))
    norm = math.sqrt(sum(v * v for v in q))
    if not 1e-3 < norm < 1e3:  # (a zero or overflowing quaternion is no rotation)
        raise Refused(name, value, "has no rotation quaternion")
    p = tuple(_scalar(name, unit, v, value) for v in _sequence(name, position, 3))
    if math.sqrt(sum(v * v for v in p)) > spec.hi:
        raise Refused(name, value, f"is farther than {spec.hi:g} from the origin")
    return tuple(v / norm for v in q), p


class ControlTable:
    """The viewer's controls by label: ``validate(name, value)`` -> the value as the control holds it, or
    Refused naming the control, the value and why."""

    def __init__(self, controls: dict[str, Control]):
        self.controls = dict(controls)

    def __contains__(self, name: str) -> bool:
        return name in self.controls

    def __getitem__(self, name: str) -> Control:
        return self.controls[name]

    def __iter__(self):
        return iter(self.controls)

    def validate(self, name: str, value):
        if name not in self.controls:
            raise Refused(name, value, "is not a control of this viewer")
        return check(name, self.controls[name], value)


__all__ = ["BUTTON", "CHECKBOX", "Control", "ControlTable", "Refused", "check", "choice", "number", "pose", "shown",
           "text", "vector"]
