"""Checkpoints of the ``fixes`` engine written by earlier layouts of its kernel state (issue 17).

:class:`~iotnav.engines.fixes.FixesEngine` is pickled for the service's checkpoints
(:mod:`iotnav.service.checkpoint`) and its fleet workers. Its scalar state ``_st`` has the layout
``S_*`` of :mod:`iotnav.engines.fixes_kernel`; the forward rows' sigma floor added two slots at
the end (``S_FLOOR_N``, ``S_FLOOR_E``), the departure test's jump tracking seven more
(``S_GOOD_*``, ``S_JUMP_*``, ``S_IN_JUMP``). A state of an earlier size (``ST_SIZE_V1``,
``ST_SIZE_V2``) is completed with the values a fresh engine starts with (0: no floor, no jump),
which the next accepted fix or re-initialisation (the floor) and the next fix the departure test
does not find displaced (the jump tracking) set; until then the forward rows report the filter's
posterior, as that version did, and the departure test's steps are measured from the time 0 (no
fix is taken for a jump's continuation). Any other size is refused.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from iotnav.engines import fixes_kernel as fk

__all__ = ["complete_state"]


def complete_state(d: dict[str, Any]) -> dict[str, Any]:
    """The pickled ``__dict__`` of a :class:`~iotnav.engines.fixes.FixesEngine`, its state in this layout.

    Parameters
    ----------
    d : dict
        The unpickled attributes (``_st``: the kernel's scalar state, ``(ST_SIZE,)``,
        ``(ST_SIZE_V2,)`` or ``(ST_SIZE_V1,)``).

    Returns
    -------
    dict
        ``d``, with ``_st`` extended by the missing slots (zeros) when it had an earlier size.

    Raises
    ------
    ValueError
        For a state of any other shape (:class:`~iotnav.service.checkpoint.CheckpointError`
        then discards the checkpoint and the device's engine starts afresh).
    """
    st = d.get("_st")
    sizes = (fk.ST_SIZE, fk.ST_SIZE_V2, fk.ST_SIZE_V1)
    if not isinstance(st, np.ndarray) or st.ndim != 1 or st.shape[0] not in sizes:
        size = st.shape if isinstance(st, np.ndarray) else type(st).__name__
        raise ValueError(
            f"fixes engine state: scalar state of shape {size}; this version reads ({fk.ST_SIZE},) "
            f"(or ({fk.ST_SIZE_V2},) before the departure test's jump tracking, ({fk.ST_SIZE_V1},) before "
            "the forward sigma floor)"
        )
    if st.shape[0] != fk.ST_SIZE:
        d = {**d, "_st": np.concatenate([st, np.zeros(fk.ST_SIZE - st.shape[0])])}
    return d
