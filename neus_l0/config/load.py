"""Configs from `confs/*.yaml` and dotted `key=value` overrides, with type checks.

A config file is a nested YAML mapping whose keys mirror the dataclass fields of
`neus_l0.config.schema`; every key is optional (missing keys keep the defaults, NeuS's
`wmask` settings). Overrides on the command line use dotted keys, e.g. ``sampler=hvs
train.iters=2000 model.sdf.hidden=64``; their values are parsed as YAML. Unknown keys and
values of the wrong type raise `ConfigError` naming the key.
"""

from __future__ import annotations

import dataclasses
import types
import typing
from pathlib import Path
from typing import Any

import yaml

from neus_l0.config.checks import validate
from neus_l0.config.duration import parse_seconds
from neus_l0.config.legacy import FORMER_NAMES, modern_override, read_legacy
from neus_l0.config.schema import (
    Config,
    SamplerConfig,
    Seconds,
)
from neus_l0.errors import ConfigError


def _find_confs_dir() -> Path:
    """The folder of the built-in configs.

    The YAMLs live in the repository's top-level ``confs/``; a wheel ships them inside the
    package as ``neus_l0/confs/`` (the build-time mapping in setup.py). So: the checkout's
    ``confs/`` beside ``pyproject.toml`` (a source tree or an editable install), else the
    installed package's own ``confs/``.
    """
    here = Path(__file__).resolve().parent.parent  # the package folder, neus_l0/
    checkout = here.parent / "confs"
    if (here.parent / "pyproject.toml").is_file() and checkout.is_dir():
        return checkout
    return here / "confs"


#: Folder holding the built-in configs (`wmask`, `womask`, `demo`, ...).
CONFS_DIR = _find_confs_dir()


#: Folder prefixes under which a config is also looked up by name in `CONFS_DIR`, so that
#: ``--conf confs/demo.yaml`` and ``--conf ./confs/demo.yaml`` work from any directory.
_CONF_PREFIXES = (Path("."), Path("confs"), Path("neus_l0") / "confs")


def _type_name(tp: Any) -> str:
    return getattr(tp, "__name__", str(tp))


def _coerce(value: Any, tp: Any, key: str) -> Any:
    """Return `value` converted to the annotated type `tp`, or raise `ConfigError`."""
    origin = typing.get_origin(tp)
    if tp is Seconds:
        return parse_seconds(value, key)
    if tp is SamplerConfig and isinstance(value, str):
        value = {"name": value}  # `sampler: hvs` is short for `sampler: {name: hvs}`
    if dataclasses.is_dataclass(tp):
        if not isinstance(value, dict):
            raise ConfigError(f"{key}: expected a mapping, got {value!r}")
        return from_dict(tp, value, prefix=key + ".")
    if origin in (typing.Union, types.UnionType):
        args = typing.get_args(tp)
        if value is None and type(None) in args:
            return None
        errors = []
        for arg in args:
            if arg is type(None):
                continue
            try:
                return _coerce(value, arg, key)
            except ConfigError as exc:
                errors.append(str(exc))
        if len(errors) > 1:  # e.g. `bool | Literal["auto"]`: name every accepted form
            accepted = "; ".join(e.split(": ", 1)[-1] for e in errors)
            raise ConfigError(f"{key}: bad value {value!r} ({accepted})")
        raise ConfigError(errors[0] if errors else f"{key}: bad value {value!r}")
    if origin is typing.Literal:
        choices = typing.get_args(tp)
        if isinstance(value, str) and value in choices:
            return value
        named = ", ".join(c for c in choices if c)
        former = f"; formerly {FORMER_NAMES[key]}" if key in FORMER_NAMES else ""
        raise ConfigError(f"{key}: unknown choice {value!r} (choose from {named}{former})")
    if origin is list:
        (item_tp,) = typing.get_args(tp)
        if isinstance(value, tuple):
            value = list(value)
        if not isinstance(value, list):
            raise ConfigError(f"{key}: expected a list, got {value!r}")
        return [_coerce(v, item_tp, f"{key}[{i}]") for i, v in enumerate(value)]
    if tp is bool:
        if isinstance(value, bool):
            return value
        raise ConfigError(f"{key}: expected true or false, got {value!r}")
    if tp is int:
        if isinstance(value, int) and not isinstance(value, bool):
            return value
        if isinstance(value, float) and value.is_integer():
            return int(value)
        raise ConfigError(f"{key}: expected an integer, got {value!r}")
    if tp is float:
        if isinstance(value, (int, float)) and not isinstance(value, bool):
            return float(value)
        if isinstance(value, str):  # PyYAML reads "5e-4" (no dot) as a string
            try:
                return float(value)
            except ValueError:
                pass
        raise ConfigError(f"{key}: expected a number, got {value!r}")
    if tp is str:
        if isinstance(value, str):
            return value
        raise ConfigError(f"{key}: expected a string, got {value!r}")
    raise ConfigError(f"{key}: unsupported type {_type_name(tp)}")  # pragma: no cover


def from_dict(cls: type, data: dict, prefix: str = "") -> Any:
    """Build dataclass `cls` from a nested mapping; unknown keys raise `ConfigError`."""
    if cls is Config:
        data = read_legacy(data)
    hints = typing.get_type_hints(cls)
    names = {f.name for f in dataclasses.fields(cls)}
    unknown = [k for k in data if k not in names]
    if unknown:
        raise ConfigError(f"unknown config key '{prefix}{unknown[0]}' "
                          f"(known under '{prefix or '.'}': {', '.join(sorted(names))})")
    base = cls()
    kwargs = {}
    for f in dataclasses.fields(cls):
        if f.name in data:
            kwargs[f.name] = _coerce(data[f.name], hints[f.name], prefix + f.name)
        else:
            kwargs[f.name] = getattr(base, f.name)
    obj = cls(**kwargs)
    validate(obj, prefix)
    return obj


def to_dict(cfg: Any) -> dict:
    """Plain nested dict of a config dataclass (for YAML and checkpoints)."""
    return dataclasses.asdict(cfg)


_MISSING = object()


def non_default(values: dict, defaults: dict) -> dict:
    """The entries of the nested dict `values` that differ from `defaults` (nested the same
    way; a key missing from `defaults` counts as differing)."""
    out = {}
    for k, v in values.items():
        base = defaults.get(k, _MISSING)
        if isinstance(v, dict) and isinstance(base, dict):
            sub = non_default(v, base)
            if sub:
                out[k] = sub
        elif base is _MISSING or v != base:
            out[k] = v
    return out


def conf_names() -> list[str]:
    """The built-in configs' names (``confs/*.yaml``), sorted."""
    return sorted(p.stem for p in CONFS_DIR.glob("*.yaml"))


def resolve_conf_path(conf: str | Path) -> Path:
    """Find a config: an existing path, else a built-in one in `CONFS_DIR`.

    A built-in config is named ``NAME``, ``NAME.yaml``, ``confs/NAME.yaml`` or
    ``./confs/NAME.yaml`` (``neus_l0/confs/NAME.yaml``, the old place, too), whatever the
    working directory.
    """
    path = Path(conf)
    if path.is_file():
        return path
    name = path.name if path.suffix in (".yaml", ".yml") else path.name + ".yaml"
    candidate = CONFS_DIR / name
    if path.parent in _CONF_PREFIXES and candidate.is_file():
        return candidate
    known = ", ".join(sorted(p.stem for p in CONFS_DIR.glob("*.yaml")))
    raise ConfigError(f"{conf}: no such config file (built-in configs: {known})")


def parse_overrides(items: list[str]) -> dict:
    """Turn ``["a.b=1", "c=x"]`` into the nested dict ``{"a": {"b": 1}, "c": "x"}``.

    Values are parsed as YAML (so `1e-4`, `true`, `[4]` work); a malformed item raises
    `ConfigError`.
    """
    out: dict = {}
    for item in map(modern_override, items):
        if "=" not in item:
            raise ConfigError(f"override '{item}' is not of the form key=value")
        key, text = item.split("=", 1)
        key = key.strip()
        if not key or any(not part for part in key.split(".")):
            raise ConfigError(f"override '{item}' has an empty key")
        try:
            value = yaml.safe_load(text) if text.strip() else ""
        except (yaml.YAMLError, RecursionError) as exc:
            raise ConfigError(f"override '{item}': value is not valid YAML "
                              f"({yaml_problem(exc)})") from None
        node = out
        parts = key.split(".")
        for part in parts[:-1]:
            if node is out and isinstance(node.get(part), str):
                node[part] = _shorthand(part, node[part])  # sampler=l0 sampler.base_inv_s=32
            node = node.setdefault(part, {})
            if not isinstance(node, dict):
                raise ConfigError(f"override '{item}' conflicts with another override")
        if node is out and isinstance(node.get(parts[-1]), dict):
            value = _merge(node[parts[-1]], {"name": value}) if _is_name(parts[-1], value) \
                else value
        node[parts[-1]] = value
    return out


def _shorthand(key: str, value: Any) -> Any:
    """``sampler: NAME`` as the block ``{name: NAME}`` (other keys and values unchanged)."""
    return {"name": value} if _is_name(key, value) else value


def _is_name(key: str, value: Any) -> bool:
    return key == "sampler" and isinstance(value, str)


def _merge(base: dict, extra: dict) -> dict:
    """`extra` over `base`, recursively. A bare sampler name over a sampler block changes its
    name only (``sampler=hvs`` keeps the file's ``sampler.l0``), and a block over a bare name
    keeps that name."""
    out = dict(base)
    for k, v in extra.items():
        if _is_name(k, v) and isinstance(out.get(k), dict):
            v = {"name": v}
        if isinstance(v, dict):  # a block merged into a shorthand: expand the shorthand
            out[k] = _shorthand(k, out.get(k))
        if isinstance(v, dict) and isinstance(out.get(k), dict):
            out[k] = _merge(out[k], v)
        else:
            out[k] = v
    return out


def yaml_problem(exc: BaseException) -> str:
    """One line for a YAML (or decoding) error: where (``line L, column C``) and what, without
    the parser's quoted context lines."""
    if isinstance(exc, yaml.MarkedYAMLError):
        mark = exc.problem_mark or exc.context_mark
        what = " ".join(str(exc.problem or exc.context or "malformed YAML").split())
        if isinstance(exc, yaml.constructor.ConstructorError) and "tag" in what:
            what += " (only plain YAML is read: no Python tags)"
        if mark is not None:
            return f"line {mark.line + 1}, column {mark.column + 1}: {what}"
        return what
    if isinstance(exc, yaml.reader.ReaderError):
        return f"byte {exc.position}: {exc.reason} (not a text file?)"
    if isinstance(exc, UnicodeDecodeError):
        return f"byte {exc.start}: not UTF-8 text"
    if isinstance(exc, RecursionError):
        return "nested too deeply"
    return " ".join(str(getattr(exc, "strerror", None) or exc).split())


def read_yaml(path: Path) -> dict:
    """Read a YAML mapping (empty file: {}), raising `ConfigError` on malformed files (one
    line: the file, the line and the problem, `yaml_problem`)."""
    try:
        data = yaml.safe_load(Path(path).read_text(encoding="utf-8"))
    except (OSError, ValueError, RecursionError, yaml.YAMLError) as exc:
        raise ConfigError(f"{path}: cannot read config: {yaml_problem(exc)}") from None
    if data is None:
        return {}
    if not isinstance(data, dict):
        raise ConfigError(f"{path}: a config file must be a mapping of keys to values")
    return data


def load_config(conf: str | Path | None = None, overrides: list[str] | None = None) -> Config:
    """Read a config file (see `resolve_conf_path`) and apply dotted overrides.

    Args:
        conf: a path, `confs/NAME.yaml` or a bare `NAME`; None for the defaults (wmask).
        overrides: ``key=value`` strings applied after the file.

    Raises:
        ConfigError: naming the file or the key that is wrong.
    """
    data: dict = {}
    source = "defaults"
    if conf is not None:
        path = resolve_conf_path(conf)
        data = read_yaml(path)
        source = str(path)
    if overrides:
        data = _merge(data, parse_overrides(overrides))
    try:
        return from_dict(Config, data)
    except ConfigError as exc:
        raise ConfigError(f"{source}: {exc}") from None


def config_from_dict(data: dict) -> Config:
    """Rebuild a `Config` from `to_dict` output (e.g. a checkpoint's)."""
    return from_dict(Config, data)


def dump_config(cfg: Config) -> str:
    """The config as YAML text (every key, so the file documents the run)."""
    return yaml.safe_dump(to_dict(cfg), sort_keys=False)
