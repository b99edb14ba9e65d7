"""The C99 firmware library (``firmware/`` at the repository root) seen from Python.

:mod:`iotnav.firmware.gen` writes the C configuration header from the engines' configuration
dataclasses and state layouts (declared once, in Python); :mod:`iotnav.firmware.host` builds the
library for the host with ``gcc`` and runs it through :mod:`ctypes`. The firmware is an edge
like the CLI (STYLE.md section 14): no engine imports this package.
"""
