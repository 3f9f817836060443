"""The settings of each synthesis method, their defaults and allowed ranges, checked by every
`build` and `from_state` (the library API; the workflow's config is checked by the same ranges
in config/schema.yaml, btf_synthesis.<method>, which tests/test_btf_synthesis.py compares with
these). A bad value raises ValueError naming the method, the key and the range.

Why the bounds (beyond the obvious): hpb `lut_size` >= 2, the LUT is interpolated between
neighbouring entries (the C kernel reads entry k + 1); hextile `exponent` <= 32, so the
largest grid weight, at least 1/3, keeps w^exponent >= 3^-32 ~ 5e-16 in float32 (beyond ~93
all three underflow to 0 and the blend is 0 / 0); `gain` strictly inside (0, 1), Gain3 takes
log(1 - gain); quilting `tolerance` >= 1, the best candidate must stay within it."""

from __future__ import annotations

import math
import numbers
from dataclasses import dataclass


@dataclass(frozen=True)
class Range:
    """A setting: `integer` or a real number in [lo, hi] (an end None: unbounded; *_open: the
    end excluded), its default and what it means."""
    default: float
    lo: float | None = None
    hi: float | None = None
    lo_open: bool = False
    hi_open: bool = False
    integer: bool = False
    note: str = ""

    def text(self) -> str:
        kind = "an integer" if self.integer else "a number"
        if self.lo is not None and self.hi is not None:
            span = f"in {'(' if self.lo_open else '['}{self.lo:g}, {self.hi:g}{')' if self.hi_open else ']'}"
        elif self.lo is not None:
            span = f"{'>' if self.lo_open else '>='} {self.lo:g}"
        elif self.hi is not None:
            span = f"{'<' if self.hi_open else '<='} {self.hi:g}"
        else:
            span = "(finite)"
        return f"{kind} {span}" + (f" ({self.note})" if self.note else "")

    def check(self, method: str, key: str, value):
        """value as int or float, or ValueError naming the method, the key and the range."""
        bad = ValueError(f"{method} setting {key!r} must be {self.text()}, got {value!r}")
        if isinstance(value, bool) or not isinstance(value, numbers.Real):
            raise bad
        v = float(value)
        if not math.isfinite(v) or (self.integer and not v.is_integer()):
            raise bad
        if self.lo is not None and (v <= self.lo if self.lo_open else v < self.lo):
            raise bad
        if self.hi is not None and (v >= self.hi if self.hi_open else v > self.hi):
            raise bad
        return int(v) if self.integer else v


SPECS = {
    "tiling": {},
    "linear": {},
    "hpb": {"lut_size": Range(128, lo=2, integer=True, note="entries of the inverse LUT")},
    "hextile": {
        "rotation": Range(1.0, lo=0, note="1 = angles over the full circle"),
        "contrast": Range(0.6, lo=0, hi=1),
        "exponent": Range(7.0, lo=0, hi=32, lo_open=True,
                          note="beyond 32 the float32 grid weights w^exponent underflow"),
        "gain": Range(0.7, lo=0, hi=1, lo_open=True, hi_open=True, note="0.5 = no Gain3"),
    },
    "quilting": {
        "scale": Range(15, lo=1, integer=True, note="exemplars per side of the quilt"),
        "block": Range(0.25, lo=0, lo_open=True,
                       note="<= 1 a fraction of the exemplar side, > 1 texels"),
        "tolerance": Range(1.1, lo=1, note="factor over the best overlap SSD"),
    },
}


def defaults(method: str) -> dict:
    return {k: r.default for k, r in SPECS[method].items()}


def check(method: str, settings: dict | None) -> dict:
    """The settings of `method` with the defaults filled in, each checked against its range;
    an unknown key (a typo such as lut_sz) is an error, not ignored."""
    spec = SPECS[method]
    settings = dict(settings or {})
    unknown = sorted(set(settings) - set(spec), key=str)
    if unknown:
        known = f"its settings are {sorted(spec)}" if spec else "it takes no settings"
        raise ValueError(f"unknown {method} setting(s) {unknown}: {known}")
    out = {k: r.check(method, k, settings.get(k, r.default)) for k, r in spec.items()}
    block = out.get("block") if method == "quilting" else None
    if block is not None and block > 1 and (not float(block).is_integer() or block < 6):
        # the schema's anyOf: 7.5 texels had been cut to 7, and 3 raised to 6, without a word
        raise ValueError(f"quilting setting 'block' above 1 is a side in texels: give a whole "
                         f"number >= 6 (or a fraction <= 1 of the exemplar side), got {block!r}")
    return out
