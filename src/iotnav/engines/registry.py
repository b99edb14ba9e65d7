"""Engines by name, for the CLI and scripts: ``make_engine("pipeline", config_path=...)``.

Each entry builds an engine from an optional TOML configuration file. Engines that are not
available in this version raise a :class:`ValueError` naming those that are.
"""

from __future__ import annotations

import dataclasses
import importlib
from collections.abc import Callable
from pathlib import Path
from typing import Any

from iotnav.engines.base import Engine
from iotnav.engines.config import config_from_toml
from iotnav.techniques.last_position import LastPositionStore, StoredPosition

#: name -> (module, engine class, config class); the config class needs ``from_toml``.
_ENGINES: dict[str, tuple[str, str, str]] = {
    "pipeline": ("iotnav.engines.pipeline", "Pipeline", "iotnav.engines.config:PipelineConfig"),
    "anchor": ("iotnav.engines.anchor", "AnchorEngine", "iotnav.engines.anchor:AnchorConfig"),
    "qekf": ("iotnav.engines.qekf", "QekfEngine", "iotnav.engines.qekf:QekfConfig"),
    "eskf": ("iotnav.engines.eskf", "EskfEngine", "iotnav.engines.eskf:EskfConfig"),
    "absfix": ("iotnav.engines.absfix", "AbsfixEngine", "iotnav.engines.absfix:AbsfixConfig"),
    "pdr": ("iotnav.engines.pdr", "PdrEngine", "iotnav.engines.pdr:PdrConfig"),
    "fixes": ("iotnav.engines.fixes", "FixesEngine", "iotnav.engines.fixes:FixesConfig"),
}

ENGINE_NAMES = tuple(_ENGINES)


def _load(spec: str) -> Any:
    module, _, name = spec.partition(":")
    return getattr(importlib.import_module(module), name)


def available_engines() -> list[str]:
    """Names of the engines importable in this installation."""
    out = []
    for name, (module, cls, _) in _ENGINES.items():
        try:
            getattr(importlib.import_module(module), cls)
        except (ImportError, AttributeError):
            continue
        out.append(name)
    return out


def make_engine(
    name: str,
    config_path: str | Path | None = None,
    stored: StoredPosition | None = None,
    store: LastPositionStore | None = None,
    smoothing: bool = False,
    integrity: bool = True,
) -> Engine:
    """Build an engine by name.

    Parameters
    ----------
    name : str
        ``pipeline``, ``anchor``, ``qekf``, ``eskf``, ``absfix``, ``pdr`` (pedestrian) or
        ``fixes`` (GNSS fixes alone).
    config_path : path-like, optional
        TOML configuration for the engine (its defaults otherwise).
    stored : StoredPosition, optional
        Last known position at boot (engines that support it).
    store : LastPositionStore, optional
        Where the engine saves the latest good position (engines that support it).
    smoothing : bool
        Keep what the RTS smoother needs (:func:`iotnav.engines.smoother.smooth_output`);
        engines without a ``smoothing`` setting raise ``ValueError``.
    integrity : bool
        Wrap the engine in :class:`iotnav.engines.integrity.IntegrityEngine`: its
        consistency is watched against the fixes, it is re-initialised (a fresh engine from the
        same arguments) when the two disagree beyond chance, and through an outage its output
        falls back to the last fix moved on at its velocity when it leaves the vehicle's
        bounded dynamics ("do no harm", issue 16). ``True`` by default: the guard keeps the
        engines' compiled block path (its per-row step is compiled too; cost in
        ``benchmarks/results/guard_cost.md``). ``False``: the engine alone. With ``smoothing``,
        and for ``fixes`` (its own gate and compiled log path), the engine is not wrapped.

    Returns
    -------
    Engine
        A fresh engine.

    Raises
    ------
    ValueError
        For an unknown or unavailable engine.
    """
    if name not in _ENGINES:
        raise ValueError(f"unknown engine {name!r}; expected one of {', '.join(_ENGINES)}")
    module, cls_name, cfg_spec = _ENGINES[name]
    try:
        cls = getattr(importlib.import_module(module), cls_name)
        cfg_cls = _load(cfg_spec)
    except (ImportError, AttributeError):
        raise ValueError(
            f"engine {name!r} is not available in this version; available: {', '.join(available_engines())}"
        ) from None
    config = None
    if config_path is not None:
        from_toml = getattr(cfg_cls, "from_toml", None)
        config = from_toml(config_path) if from_toml else config_from_toml(config_path, cfg_cls(), name)
    if smoothing:
        config = _with_smoothing(name, config if config is not None else cfg_cls())
    kwargs: dict[str, Any] = {"config": config}
    if name in ("pipeline", "fixes"):
        kwargs.update(stored=stored, store=store)
    factory: Callable[..., Engine] = cls
    args = {k: v for k, v in kwargs.items() if v is not None or k == "config"}
    # the smoother post-processes the engine's own states; fixes runs its own compiled log path
    if not integrity or smoothing or name == "fixes":
        return factory(**args)
    import functools

    from iotnav.engines.integrity import IntegrityEngine

    return IntegrityEngine(functools.partial(factory, **args))  # picklable (fleet workers)


def _with_smoothing(name: str, config: Any) -> Any:
    """``config`` with ``smoothing=True`` (at the top or in its ``kf`` or ``fusion`` section)."""
    for path in ((), ("kf",), ("fusion",)):
        target = config
        for part in path:
            target = getattr(target, part, None)
        if dataclasses.is_dataclass(target) and any(
            f.name == "smoothing" for f in dataclasses.fields(target)
        ):
            new = dataclasses.replace(target, smoothing=True)  # type: ignore[type-var]
            return dataclasses.replace(config, **{path[0]: new}) if path else new
    raise ValueError(
        f"engine {name!r} does not support --smooth (no smoothing log): anchor, qekf, eskf and pipeline do"
    )


#: Walking: GNSS speed while moving at most this (m/s; a brisk walk is 1.5-2 m/s, jogging 3).
_WALK_MAX_SPEED_MPS = 3.0
#: Walking cadence, steps per second while moving (1.5-2.5 Hz walking, :mod:`iotnav.techniques.steps`).
_WALK_CADENCE_HZ = (1.2, 2.8)


def _looks_like_walking(log: Any, span_s: float = 120.0) -> tuple[bool, str]:
    """Whether the first ``span_s`` of moving GNSS show a walker: slow, with a walking cadence.

    Slow: the 95th percentile of the GNSS speed while moving (> 0.5 m/s) is at most 3 m/s.
    Cadence: the pdr engine's step detector finds 1.2-2.8 steps per second of moving time.
    """
    import numpy as np

    from iotnav.engines.pdr import PDR_STEPS
    from iotnav.techniques.steps import StepDetector

    g = log.gnss[log.gnss["valid"].to_numpy(bool)]
    sp = g["speed_mps"].to_numpy(float)
    vn, ve = g["vn"].to_numpy(float), g["ve"].to_numpy(float)
    sp = np.where(np.isfinite(sp), sp, np.hypot(vn, ve))
    tg = g["t"].to_numpy(float)
    moving = np.isfinite(sp) & (sp > 0.5)
    if moving.sum() < 5:
        return False, "no GNSS speed of a moving device"
    top = float(np.percentile(sp[moving], 95))
    if top > _WALK_MAX_SPEED_MPS:
        return False, f"GNSS speed up to {top:.1f} m/s (95th percentile) is faster than walking"
    t0 = float(tg[moving][0])
    imu = log.imu[(log.imu["t"] >= t0) & (log.imu["t"] < t0 + span_s)]
    if len(imu) < 100:
        return False, "too little IMU while moving"
    det = StepDetector(PDR_STEPS)  # the pdr engine's detector (hand-held threshold)
    acc = imu[["acc_x", "acc_y", "acc_z"]].to_numpy(float)
    steps = [
        e.t for t, a in zip(imu["t"].to_numpy(float), acc, strict=True) if (e := det.update(t, a)) is not None
    ]
    ti = imu["t"].to_numpy(float)
    k = np.clip(np.searchsorted(tg, ti) - 1, 0, len(tg) - 1)
    moving_s = float(np.sum(np.diff(ti)[moving[k][:-1]]))
    if moving_s <= 10.0 or len(steps) < 10:
        return False, f"{len(steps)} steps in {moving_s:.0f} s of moving: no walking cadence"
    cadence = len(steps) / moving_s
    lo, hi = _WALK_CADENCE_HZ
    if lo <= cadence <= hi:
        return True, f"{cadence:.2f} steps/s while moving at up to {top:.1f} m/s"
    return False, f"{cadence:.2f} steps/s while moving: not a walking cadence"


def default_engine(log: Any) -> tuple[str, str]:
    """The engine that measures best for the inputs a log holds, and why.

    The choice follows the measured cases of issue 16 (``benchmarks/results/cases.md``):

    * IMU and GNSS of a vehicle (or of an unknown platform): ``eskf``, the best engine through
      outages on the drive started in motion with a raw gyro and a turned sensor (median drift
      2.1 % / 1.4 % over 15 / 30 s outages, the next best 28 %), and on par with the last fix
      moved on at its velocity on the Husky, where the others are 2-10 times worse;
    * IMU and GNSS of a walker (slow, with a steady step cadence, :func:`_looks_like_walking`):
      ``pdr`` (walk_0827: 15.6 % / 10.4 % where every other engine exceeds 100 %);
    * a magnetometer changes nothing in the choice (eskf uses it when present);
    * no IMU: ``fixes`` (GNSS alone) when that engine is installed, else ``pipeline`` (which then
      reports the fixes);
    * no GNSS: ``pipeline`` (last-position boot and dead reckoning from it).

    Parameters
    ----------
    log : Log
        The merged input.

    Returns
    -------
    name, reason : str
        An engine of :func:`available_engines` and one sentence saying why.
    """
    avail = set(available_engines())
    has_imu, has_gnss = len(log.imu) > 0, len(log.gnss) > 0
    mag = " (with magnetometer, used by eskf)" if len(log.mag) else ""
    if not has_imu:
        if "fixes" in avail:
            return "fixes", "no IMU samples: GNSS fixes alone"
        return "pipeline", "no IMU samples and no GNSS-only engine installed: the pipeline reports the fixes"
    if not has_gnss:
        return "pipeline", "no GNSS: the pipeline dead-reckons from a stored last position"
    walking, why = _looks_like_walking(log)
    if walking and "pdr" in avail:
        return "pdr", f"IMU + GNSS of a walker ({why}): pedestrian dead reckoning measures best{mag}"
    return "eskf", f"IMU + GNSS, vehicle or unknown platform ({why}): eskf measures best{mag}"
