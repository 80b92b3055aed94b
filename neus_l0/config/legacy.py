"""The keys old configs and checkpoints used, read into today's schema (the one place)."""

from __future__ import annotations

import warnings

from neus_l0.config.schema import L0_KINDS

#: Old `render.*` sampler keys and the `sampler.*` keys they now mean (`read_legacy`).
LEGACY_SAMPLER_KEYS: dict[str, str] = {
    "point_weights": "placement",
    "weights_as_density": "as_density",
    "l0_pad": "pad",
}
#: The L0 samplers' options, once keys of the sampler block itself, now of its ``l0`` block.
L0_KEYS = ("kind", "masses", "pad", "pad_mode", "blur", "placement", "as_density")
#: Today's dotted keys and the names they had, for errors about a value given the old way.
FORMER_NAMES: dict[str, str] = {
    **{f"sampler.l0.{new}": f"render.{old}" for old, new in LEGACY_SAMPLER_KEYS.items()},
    **{f"sampler.l0.{key}": f"sampler.{key}" for key in L0_KEYS
       if key not in LEGACY_SAMPLER_KEYS.values()},
}

#: Keys that once did something and no longer do: read and dropped, with one warning.
#: ``sampler.compile`` (was ``render.compile_sampler``) compiled the draw alone; the whole
#: training step compiles with ``train.compile=true``, the draw included.
RETIRED_KEYS: dict[str, tuple[str, ...]] = {
    "render": ("compile_sampler",),
    "sampler": ("compile",),
}


def _drop_retired(data: dict) -> dict:
    """`data` without the `RETIRED_KEYS`; one warning names those it held."""
    dropped = []
    out = dict(data)
    for block, keys in RETIRED_KEYS.items():
        sub = out.get(block)
        if isinstance(sub, dict) and any(k in sub for k in keys):
            out[block] = {k: v for k, v in sub.items() if k not in keys}
            dropped += [f"{block}.{k}" for k in keys if k in sub]
    if dropped:
        warnings.warn(f"{', '.join(dropped)}: no longer has an effect and is ignored "
                      "(train.compile=true compiles the whole training step)", FutureWarning,
                      stacklevel=4)
    return out


#: The fields of a sampler block dumped before `masses` existed (session 3's `SamplerConfig`).
_DUMPED_SAMPLER_KEYS = frozenset({"name", "kind", "pad", "pad_mode", "blur", "placement",
                                  "as_density", "base_inv_s"})


def modern_override(item: str) -> str:
    """A ``key=value`` override in today's spelling: ``sampler.pad=0.1`` is
    ``sampler.l0.pad=0.1`` (the L0 options' own block)."""
    key, sep, value = item.partition("=")
    parts = key.strip().split(".")
    if sep and len(parts) == 2 and parts[0] == "sampler" and parts[1] in L0_KEYS:
        return f"sampler.l0.{parts[1]}={value}"
    return item


def _nest_l0(sampler: dict) -> dict:
    """The sampler block with its L0 options (`L0_KEYS`) moved into its ``l0`` block (where
    both are given, the ``l0`` block's value wins)."""
    flat = {k: sampler[k] for k in L0_KEYS if k in sampler}
    if not flat:
        return sampler
    nested = sampler.get("l0")
    nested = dict(nested) if isinstance(nested, dict) else {}
    out = {k: v for k, v in sampler.items() if k not in L0_KEYS}
    out["l0"] = {**flat, **nested}
    return out


def _read_flat(data: dict) -> dict:
    """Move the old `render.*` sampler keys (`LEGACY_SAMPLER_KEYS`) into the sampler block.

    The one place where old configs and checkpoints are read: ``render.l0_pad`` becomes
    ``sampler.pad`` and so on; a bare ``sampler: NAME`` becomes ``{name: NAME}``. Where both
    spellings are given, the new ``sampler.*`` key wins. ``render.l0_pad`` also sets
    ``blur: true`` and ``pad_mode: absolute`` (unless given), which is what the old code ran,
    so old configs and checkpoints keep their meaning; so does a whole sampler block dumped
    before ``masses`` existed (every field of that time, `_DUMPED_SAMPLER_KEYS`, and no
    ``masses``: it gets ``masses: interpolant``). A hand-written block (``{name: hvs,
    base_inv_s: 128}``) is not a dump and keeps the default.
    """
    data = _drop_retired(data)
    stored = data.get("sampler")
    if (isinstance(stored, dict) and _DUMPED_SAMPLER_KEYS <= stored.keys()
            and "masses" not in stored):
        # a whole block dumped before `masses` existed: those runs drew from the interpolant
        data = {**data, "sampler": {**stored, "masses": "interpolant"}}
    render = data.get("render")
    if not isinstance(render, dict) or not any(k in render for k in LEGACY_SAMPLER_KEYS):
        return data
    sampler = data.get("sampler", {})
    sampler = {"name": sampler} if isinstance(sampler, str) else dict(sampler or {})
    render = dict(render)
    for old, new in LEGACY_SAMPLER_KEYS.items():
        if old in render:
            sampler.setdefault(new, render.pop(old))
            if old == "l0_pad":  # the old code always blurred, with an absolute pad
                sampler.setdefault("blur", True)
                sampler.setdefault("pad_mode", "absolute")
    if sampler.get("name", "l0") in L0_KINDS:  # the old code drew from the interpolant
        sampler.setdefault("masses", "interpolant")
    return {**data, "render": render, "sampler": sampler}


def read_legacy(data: dict) -> dict:
    """Today's config mapping from any older one (`_read_flat`, then the L0 options into
    ``sampler.l0``): the one place where old configs and checkpoints are read."""
    data = _read_flat(data)
    sampler = data.get("sampler")
    if isinstance(sampler, dict):
        data = {**data, "sampler": _nest_l0(sampler)}
    return data
