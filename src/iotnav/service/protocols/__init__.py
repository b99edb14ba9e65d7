"""Protocol decoders: pure functions from received bytes to :class:`Fix` records plus the answer.

Each decoder returns a :class:`Decoded` (records, the bytes to answer, bytes consumed), an
:class:`Incomplete` when a stream framing needs more bytes, or a :class:`Rejected` with a
machine-readable reason; it never raises on any input (fuzzed with hypothesis in
``tests/test_service_protocols.py``).
"""

from iotnav.service.protocols.common import Decoded, Fix, Incomplete, Rejected

__all__ = ["Decoded", "Fix", "Incomplete", "Rejected"]
