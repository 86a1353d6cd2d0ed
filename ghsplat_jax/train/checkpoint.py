"""Checkpoints: the state pytree's leaves in one .npz (atomic), with the step, the pair
capacity and the resolved config, so `--resume` continues bit for bit."""

from __future__ import annotations

import json
import os
from pathlib import Path

import jax
import numpy as np

from ghsplat_jax.io_utils import atomic_write


class CheckpointError(ValueError):
    """A checkpoint that cannot be written or restored; the message names the file."""


def _key(path) -> str:
    return jax.tree_util.keystr(path)


def save_checkpoint(path: str | os.PathLike, state, extra: dict, aux=None) -> Path:
    """Write `state` (any pytree), a JSON-able `extra` dict and an optional second pytree `aux`
    (a strategy's state; read back with `load_aux`); refuses non-finite live values."""
    path = Path(path)
    leaves = jax.tree_util.tree_flatten_with_path(state)[0]
    arrays = {}
    for i, (_p, leaf) in enumerate(leaves):
        arrays[f"leaf_{i:04d}"] = np.asarray(leaf)
    aux_leaves = jax.tree_util.tree_flatten_with_path(aux)[0] if aux is not None else []
    for i, (_p, leaf) in enumerate(aux_leaves):
        arrays[f"aux_{i:04d}"] = np.asarray(leaf)
    active = np.asarray(state.active)
    for name in ("means", "quats", "log_scales", "opacity_logits", "sh_dc", "sh_rest"):
        values = np.asarray(getattr(state.params, name))[active]
        if not np.all(np.isfinite(values)):
            raise CheckpointError(f"{path}: refusing to write non-finite {name} to a checkpoint")
    meta = dict(extra, keys=[_key(p) for p, _ in leaves])
    if aux is not None:
        meta["aux_keys"] = [_key(p) for p, _ in aux_leaves]
    arrays["meta_json"] = np.frombuffer(json.dumps(meta).encode(), np.uint8)
    with atomic_write(path, "wb") as fh:
        np.savez(fh, **arrays)
    return path


def read_meta(path: str | os.PathLike) -> dict:
    path = Path(path)
    try:
        with np.load(path) as z:
            return json.loads(bytes(z["meta_json"]).decode())
    except (OSError, KeyError, ValueError) as exc:
        raise CheckpointError(f"{path}: not a readable checkpoint ({exc})") from None


def load_checkpoint(path: str | os.PathLike, template) -> tuple[object, dict]:
    """Restore a pytree with the structure of `template` (shapes from the file)."""
    path = Path(path)
    meta = read_meta(path)
    paths, treedef = jax.tree_util.tree_flatten_with_path(template)
    keys = [_key(p) for p, _ in paths]
    if keys != meta["keys"]:
        raise CheckpointError(f"{path}: the checkpoint's state layout does not match this version's")
    with np.load(path) as z:
        leaves = [jax.numpy.asarray(z[f"leaf_{i:04d}"]) for i in range(len(keys))]
    for (p, t), leaf in zip(paths, leaves):
        if np.ndim(t) != leaf.ndim:
            raise CheckpointError(f"{path}: leaf {_key(p)} has rank {leaf.ndim}, expected {np.ndim(t)}")
    return jax.tree_util.tree_unflatten(treedef, leaves), meta


def load_aux(path: str | os.PathLike, template):
    """The `aux` pytree saved with a checkpoint, with the structure of `template`; None when the
    file has none (a checkpoint written before strategies kept state). Entries the template has
    and the file lacks (state a newer version of the strategy keeps) take the template's values."""
    path = Path(path)
    meta = read_meta(path)
    if "aux_keys" not in meta:
        return None
    paths, treedef = jax.tree_util.tree_flatten_with_path(template)
    keys = [_key(p) for p, _ in paths]
    saved = list(meta["aux_keys"])
    if not set(saved) <= set(keys):
        raise CheckpointError(f"{path}: the saved strategy state {saved} does not match this "
                              f"strategy's {keys} (was the run started with another strategy?)")
    with np.load(path) as z:
        stored = {k: jax.numpy.asarray(z[f"aux_{i:04d}"]) for i, k in enumerate(saved)}
    return jax.tree_util.tree_unflatten(treedef, [stored.get(k, leaf) for k, (_, leaf) in zip(keys, paths)])
