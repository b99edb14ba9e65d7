"""Engines: compositions of techniques behind one ``step()`` (STYLE §7).

:mod:`~iotnav.engines.base` holds the sample types, the engine protocol, the output record and
the batch runner; :mod:`~iotnav.engines.pipeline` wires Forno et al. 2020 Fig. 1.
"""

from iotnav.engines.base import Engine, GnssSample, ImuSample, MagSample, Output, run_batch
from iotnav.engines.config import PipelineConfig
from iotnav.engines.pipeline import Pipeline

__all__ = [
    "Engine",
    "GnssSample",
    "ImuSample",
    "MagSample",
    "Output",
    "Pipeline",
    "PipelineConfig",
    "run_batch",
]
