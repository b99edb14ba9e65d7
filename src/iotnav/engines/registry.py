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
        ``pipeline``, ``anchor``, ``qekf``, ``eskf``, ``absfix`` or ``pdr`` (pedestrian).
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
        Wrap the engine in :class:`iotnav.engines.integrity.IntegrityEngine` (default): its
        consistency is watched against the fixes, it is re-initialised (a fresh engine from the
        same arguments) when the two disagree beyond chance, and through an outage its output
        falls back to the last fix moved on at its velocity when it leaves the vehicle's
        bounded dynamics ("do no harm", issue 16). ``False``: the engine alone.

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
    if name == "pipeline":
        kwargs.update(stored=stored, store=store)
    factory: Callable[..., Engine] = cls
    args = {k: v for k, v in kwargs.items() if v is not None or k == "config"}
    if not integrity:
        return factory(**args)
    from iotnav.engines.integrity import IntegrityEngine

    return IntegrityEngine(lambda: factory(**args))


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
