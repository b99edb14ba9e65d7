"""The ``eskf`` maths under its former name: :mod:`iotnav.engines.eskf.models`."""

from iotnav.engines.eskf.models import *  # noqa: F403
