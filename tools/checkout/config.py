"""The checkout's configuration: ``tools/checkout/checkout_default.toml`` merged with a user file."""

from __future__ import annotations

import copy
import fnmatch
import tomllib
from pathlib import Path
from typing import Any

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
    try:
        with open(path, "rb") as f:
            return tomllib.load(f)
    except OSError as err:
        raise ConfigError(f"checkout configuration {path}: {err.strerror}") from err
    except tomllib.TOMLDecodeError as err:
        raise ConfigError(f"checkout configuration {path}: {err}") from err


class CheckoutConfig:
    """Nested tables of the TOML file with typed, named look-ups.

    ``cfg.num("joints", "rate_rad_s")`` raises :class:`ConfigError` naming the key when it
    is missing or not a number; ``cfg.joint("wrist_roll", "move_s")`` applies the
    ``[joints.<joint>]`` override.
    """

    def __init__(self, data: dict, source: str = "") -> None:
        self.data = data
        self.source = source
        groups = self.get("checkout", "groups")
        bad = [g for g in groups if g not in GROUPS]
        if bad:
            raise ConfigError(f"{source}: [checkout] groups: unknown {bad}; known: {', '.join(GROUPS)}")

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
