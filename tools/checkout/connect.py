"""The checkout's connection to a live service: :func:`attach_waiting` (wait for one,
with notices, bounded) and :class:`ServiceLink` (reattach after a restart).

Both are the tools' one attach/wait/reattach helper, :mod:`tools.attach`; this module
names what the checkout uses of it.
"""

from __future__ import annotations

from tools.attach import ServiceLink, attach_waiting, service_problem

__all__ = ["ServiceLink", "attach_waiting", "service_problem"]
