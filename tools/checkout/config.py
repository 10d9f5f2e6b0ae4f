"""The checkout's configuration: ``tools/checkout/checkout_default.toml`` merged with a user file."""

from __future__ import annotations

import copy
import fnmatch
from pathlib import Path
from typing import Any, Literal

import msgspec

from pfma import config
from pfma.errors import ConfigError

DEFAULT_PATH = Path(__file__).with_name("checkout_default.toml")
#: every group the checkout knows, in run order
GROUPS: tuple[str, ...] = ("resolvers", "adc", "links", "hand", "pio", "matrix", "joints")


def _merge(base: dict, over: dict) -> dict:
    out = dict(base)
    for k, v in over.items():
        out[k] = _merge(out[k], v) if isinstance(v, dict) and isinstance(out.get(k), dict) else v
    return out


def _read(path: Path) -> dict:
    text = config.read_text(path, "checkout configuration")
    return config.parse_toml(text, f"checkout configuration {path}")


# The keys checked when the configuration is made (the rest are looked up, by name, when
# a check runs: CheckoutConfig.get/num/joint)
class _AdcGroup(msgspec.Struct, forbid_unknown_fields=True):
    name: str
    match: list[str]
    quantity: Literal["value", "volts"]
    low: float
    high: float


class _Adc(msgspec.Struct):
    group: list[_AdcGroup] = msgspec.field(default_factory=list)


class _Checkout(msgspec.Struct):
    groups: list[Literal[GROUPS]]  # type: ignore[valid-type]


class _CheckoutFile(msgspec.Struct):
    checkout: _Checkout
    adc: _Adc = msgspec.field(default_factory=_Adc)


_MESSAGES = {
    "checkout.groups[]": "[checkout] groups: unknown [{value!r}]; known: " + ", ".join(GROUPS),
    "adc.group[].quantity": "[[adc.group]] {name}: quantity must be 'value' or 'volts'",
}


class CheckoutConfig:
    """Nested tables of the TOML file with typed, named look-ups.

    ``cfg.num("joints", "rate_rad_s")`` raises :class:`ConfigError` naming the key when it
    is missing or not a number; ``cfg.joint("wrist_roll", "move_s")`` applies the
    ``[joints.<joint>]`` override.
    """

    def __init__(self, data: dict, source: str = "") -> None:
        self.data = data
        self.source = source
        config.convert(data, _CheckoutFile, source=f"checkout configuration {source}", messages=_MESSAGES,
                       error=lambda p: ConfigError(str(p)))

    def get(self, *keys: str) -> Any:
        d: Any = self.data
        for i, k in enumerate(keys):
            if not isinstance(d, dict) or k not in d:
                raise ConfigError(f"checkout configuration {self.source}: missing "
                                  f"[{'.'.join(keys[:i]) or 'top'}] {k}")
            d = d[k]
        return d

    def num(self, *keys: str) -> float:
        v = self.get(*keys)
        if isinstance(v, bool) or not isinstance(v, (int, float)):
            raise ConfigError(f"checkout configuration {self.source}: [{'.'.join(keys[:-1])}] "
                              f"{keys[-1]} = {v!r} is not a number")
        return float(v)

    def joint(self, joint: str, key: str) -> Any:
        """A ``[joints]`` value with the ``[joints.<joint>]`` override applied."""
        over = self.data.get("joints", {}).get(joint)
        if isinstance(over, dict) and key in over:
            return over[key]
        return self.get("joints", key)

    def adc_group(self, signal: str) -> dict | None:
        """The first ``[[adc.group]]`` whose patterns match ``signal`` (None: no idle range)."""
        for g in self.get("adc", "group"):
            if any(fnmatch.fnmatchcase(signal, p) for p in g.get("match", [])):
                for k in ("name", "quantity", "low", "high"):
                    if k not in g:
                        raise ConfigError(f"checkout configuration {self.source}: [[adc.group]] "
                                          f"{g.get('name', g.get('match'))} lacks {k}")
                if g["quantity"] not in ("value", "volts"):
                    raise ConfigError(f"checkout configuration {self.source}: [[adc.group]] "
                                      f"{g['name']}: quantity must be 'value' or 'volts'")
                return g
        return None

    def as_dict(self) -> dict:
        return copy.deepcopy(self.data)


def load_checkout_config(path: str | Path | None = None) -> CheckoutConfig:
    """The default configuration, with ``path`` (if given) merged over it key by key."""
    data = _read(DEFAULT_PATH)
    source = str(DEFAULT_PATH)
    if path is not None:
        data = _merge(data, _read(Path(path)))
        source = f"{path} (over {DEFAULT_PATH.name})"
    return CheckoutConfig(data, source)
