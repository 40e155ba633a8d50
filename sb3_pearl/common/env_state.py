"""Mid-episode state of a VecEnv's envs, saved with a model so that a loaded run continues the open episodes.

SB3 saves no env state: a loaded model resets its envs before training, so a run split by save /
load differs from the unsplit one whenever the split falls inside an episode (Fine-Tune's SAC loop
always collects across episodes). :func:`capture_env_state` snapshots every layer of every env of a
:class:`~stable_baselines3.common.vec_env.DummyVecEnv` (each wrapper's attributes: time-limit counters,
the task in force and the pending one, the env's ``np_random``, inner envs a family composes, MuJoCo's
``MjData``, highway-env's road and vehicles) and :func:`restore_env_state` writes it back into an env of the same structure.

How it stays generic and correct:

- one pickle holds all layers of one env, so objects shared between layers stay shared; references
  to the live layers themselves (highway-env's observation type points back to its env) and to
  MuJoCo's ``MjModel`` are saved as references and resolve to the *new* env's objects on restore;
- ``MjData`` is copied into the new env's ``MjData`` (``mujoco.mj_copyData``), so the renderer and
  everything else holding it stays valid, and the next ``mj_step`` is bit-identical (warm start and
  derived quantities included);
- attributes that do not pickle and hold no dynamics (Monitor's CSV writer, renderers and viewers)
  are left as they are in the new env; any other attribute that does not pickle makes the capture
  return None with a warning naming it (a loaded run then resets its envs, as SB3 does).

A ``SubprocVecEnv`` or another VecEnv type is not captured (its envs live in other processes).
The snapshot is zlib-compressed (MuJoCo's ``MjData`` holds a mostly empty arena).

A pickled ``MjData`` carries its model serialized by the MuJoCo that wrote it, and another MuJoCo release may refuse
to read it ("Invalid serialized mjModel", seen between 4.0.0 and 4.0.1): the snapshot records the MuJoCo version
(``mujoco``) and :func:`restore_env_state` raises :class:`EnvStateError` naming both versions when it cannot read a
snapshot (``make setup`` pins MuJoCo in ``constraints.txt`` so that committed checkpoints stay readable).
"""

from __future__ import annotations

import io
import pickle
import sys
import warnings
import zlib
from typing import Any

import gymnasium as gym
from stable_baselines3.common.vec_env import DummyVecEnv, VecEnv

# Attributes with no dynamics that need not (and often cannot) be pickled: kept from the new env.
SKIPPED_ATTRIBUTES = frozenset({"env", "results_writer", "mujoco_renderer", "viewer", "renderer", "_renderer"})


class EnvStateError(ValueError):
    """A saved env snapshot that cannot be read here (written by another MuJoCo release, most often)."""


def _mujoco_version() -> str | None:
    """The version of the MuJoCo loaded in this process (None: not loaded, so no MuJoCo object was snapshotted)."""
    module = sys.modules.get("mujoco")
    return getattr(module, "__version__", None) if module is not None else None


def _layers(env: gym.Env) -> list[Any]:
    """
    Every env object of one env, outermost first: the wrapper chain and any env held as an attribute
    (a family that composes an inner env, as the point-maze family holds gymnasium-robotics' maze).
    """
    layers: list[Any] = []
    pending: list[Any] = [env]
    while pending:
        layer = pending.pop(0)
        if any(layer is seen for seen in layers):
            continue
        layers.append(layer)
        pending.extend(value for value in vars(layer).values() if isinstance(value, gym.Env))
    return layers


def _mujoco() -> Any:
    """The mujoco module, imported on first use (``import sb3_pearl`` picks a headless GL backend before it loads)."""
    import mujoco

    return mujoco


def dummy_vec_env(env: VecEnv | None) -> DummyVecEnv | None:
    """The DummyVecEnv under VecEnv wrappers (VecNormalize, VecMonitor, ...), or None for other VecEnvs."""
    base = env.unwrapped if env is not None else None
    return base if isinstance(base, DummyVecEnv) else None


class _Pickler(pickle.Pickler):
    """Pickles one env's layer attributes; the live layers and MuJoCo models become references by position."""

    def __init__(self, file: io.BytesIO, live: dict[int, tuple[str, int]]) -> None:
        super().__init__(file, protocol=pickle.HIGHEST_PROTOCOL)
        self.live = live

    def persistent_id(self, obj: Any) -> tuple[str, int] | None:
        return self.live.get(id(obj))


class _Unpickler(pickle.Unpickler):
    def __init__(self, file: io.BytesIO, live: dict[tuple[str, int], Any]) -> None:
        super().__init__(file)
        self.live = live

    def persistent_load(self, pid: Any) -> Any:
        return self.live[tuple(pid)]


def _live_objects(layers: list[Any]) -> dict[tuple[str, int], Any]:
    """Objects referenced by position, not copied: every layer, and each layer's MuJoCo model."""
    live: dict[tuple[str, int], Any] = {("layer", i): layer for i, layer in enumerate(layers)}
    mj_model = _mujoco().MjModel
    for i, layer in enumerate(layers):
        for value in vars(layer).values():
            if isinstance(value, mj_model):
                live["mjmodel", i] = value
    return live


def _capture_one(env: gym.Env, index: int) -> bytes | None:
    layers = _layers(env)
    live = _live_objects(layers)
    by_id = {id(obj): key for key, obj in live.items()}
    attributes = [{k: v for k, v in vars(layer).items() if k not in SKIPPED_ATTRIBUTES} for layer in layers]
    chain = [type(layer).__qualname__ for layer in layers]
    file = io.BytesIO()
    try:
        _Pickler(file, by_id).dump((chain, attributes))
    except Exception as error:  # find the attribute to name in the warning
        for layer, values in zip(layers, attributes):
            for key, value in values.items():
                try:
                    _Pickler(io.BytesIO(), by_id).dump(value)
                except Exception:
                    warnings.warn(
                        f"The state of env {index} cannot be saved: {type(layer).__name__}.{key} does not pickle "
                        f"({type(error).__name__}: {error}). A model loaded from this save resets its envs before "
                        "training (SB3's behaviour), so a resumed run is not bit-identical to an unsplit one.",
                        stacklevel=4,
                    )
                    return None
        raise
    return zlib.compress(file.getvalue(), 1)


def capture_env_state(env: VecEnv | None) -> dict[str, Any] | None:
    """
    Snapshot the mid-episode state of every env of a DummyVecEnv (see the module docstring).

    :param env: the model's VecEnv
    :return: one compressed snapshot per env (``envs``) and the DummyVecEnv's seeds and options pending for its
        next reset; None when there is no env, for another VecEnv type, or when an env does not pickle
    """
    dummy = dummy_vec_env(env)
    if dummy is None:
        return None
    snapshots = [_capture_one(e, i) for i, e in enumerate(dummy.envs)]
    if any(s is None for s in snapshots):
        return None
    return {"envs": snapshots, "seeds": list(dummy._seeds), "options": list(dummy._options), "mujoco": _mujoco_version()}


def restore_env_state(env: VecEnv | None, state: dict[str, Any]) -> bool:
    """
    Write a snapshot of :func:`capture_env_state` into an env of the same structure.

    :param env: the model's VecEnv
    :param state: the snapshot
    :return: whether the state was restored (False, and nothing changed, when the env does not fit:
        another VecEnv type, another number of envs, or another wrapper chain)
    :raises EnvStateError: (nothing changed) when a snapshot cannot be read here, with the MuJoCo versions that wrote
        and that read it
    """
    dummy = dummy_vec_env(env)
    snapshots = state["envs"]
    if dummy is None or len(dummy.envs) != len(snapshots):
        return False
    decoded = []
    for e, snapshot in zip(dummy.envs, snapshots):
        layers = _layers(e)
        try:
            chain, attributes = _Unpickler(io.BytesIO(zlib.decompress(snapshot)), _live_objects(layers)).load()
        except (ValueError, pickle.UnpicklingError, EOFError, zlib.error) as error:
            saved, installed = state.get("mujoco"), _mujoco_version()
            if saved is not None and saved == installed:
                raise  # the same MuJoCo wrote it: not a version mismatch, a bug to see whole
            writer = f"MuJoCo {saved}" if saved else "a MuJoCo whose version it does not record (an older file)"
            raise EnvStateError(
                f"the envs' saved mid-episode state cannot be read here ({type(error).__name__}: {error}); it was written "
                f"with {writer} and this process has MuJoCo {installed or '(not loaded)'}: install the version that "
                f"wrote it (pip install mujoco=={saved or '<version>'}; a harness run's result.json or the constraints.txt "
                "of its commit names it) to continue its episodes exactly"
            ) from error
        if chain != [type(layer).__qualname__ for layer in layers]:
            return False
        decoded.append((layers, attributes))
    mujoco = _mujoco()
    for layers, attributes in decoded:
        for layer, values in zip(layers, attributes):
            for key, value in values.items():
                current = vars(layer).get(key)
                if isinstance(value, mujoco.MjData) and isinstance(current, mujoco.MjData):
                    mujoco.mj_copyData(current, layer.model, value)  # in place: whoever holds the MjData keeps it
                else:
                    vars(layer)[key] = value  # the attribute itself, past any property
    # The seeds SB3's load() just set (set_random_seed) must not reseed the running envs at their next reset.
    dummy._seeds, dummy._options = list(state["seeds"]), list(state["options"])
    return True
