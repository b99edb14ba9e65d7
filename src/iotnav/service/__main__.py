"""``python -m iotnav.service CONFIG.toml`` (see :func:`iotnav.service.app.main`)."""

from iotnav.service.app import main

main()
