"""PFMA rack I/O service: shared pieces (errors, clock, rack configuration, CLI).

The hardware-facing code lives in the top-level packages ``drivers``, ``fakes``,
``ioservice``, ``controller`` and ``calibration``; this package holds what all of
them share and the ``pfma`` command.
"""

__version__ = "0.1.0"
