"""The controller's world model: the IRSS "blackboard" of named, typed variables.

Source: IRSS report (Martin Marietta, IRSS Phase II final report) sections 2.2.2 (world
model rules 1-4), 2.2.3 (communications segment, world model locked out while it is
updated), 2.3.5 "Access Tools" (get-task-inputs, get-state-variable, post-task-outputs,
post-state-variable; asynchronous user-interface access) and 2.3.6 (areas; "Assurance of
World Model Access Validity": the temporary queue and the COMM-INTERRUPT / IN-COMM-FRAME
flags), 2.2.8 (display windows cannot modify data "without proper access keys").

Rules kept here:

- every variable has a name, an area (:data:`AREAS`), a numpy dtype and shape, units, a
  doc string and exactly one writer (report rule 3); a post by anyone else is refused
  with an error that names the owner;
- every variable holds a valid value from :meth:`WorldModel.create` on (rule 4); every
  posted value is checked (shape, dtype range, finite floats) before it is queued;
- posts are queued and applied all together by :meth:`WorldModel.communications_segment`
  under one sequence lock, so a reader (this process or another) never sees half a frame;
- a user-interface write (:meth:`WorldModel.set_user`, ``pfma wm set``) is allowed only for
  variables that declare it (``VarSpec.user``: task outputs, layer commands and statuses
  never, control-law parameters only while powered down, requests always), needs the access
  key, and goes through a small request ring in the segment that the owner applies, after
  checking all of it again, at its next communications segment.

The package, cut along those seams (``from controller.worldmodel import X`` gives all of it):

- :mod:`controller.worldmodel.spec`: variable specifications (:class:`VarSpec`, the areas,
  who may set what, :func:`coerce`, :func:`coerce_user`) and the errors;
- :mod:`controller.worldmodel.segment`: the shared-memory segment format (header fields,
  request-slot layout, the variable table's layout and decoding, :func:`list_segments`);
- :mod:`controller.worldmodel.requests`: the user-request ring (keyed user writes);
- :mod:`controller.worldmodel.model`: the :class:`WorldModel` itself (opening, reading, the
  queued posts and the communications segment, with its IRSS queue logic).

The segment layout (header, spec JSON, request ring, seqlocked data body) is in
``docs/world-model.md``. The sequence lock, the shared-memory open without the
resource-tracker, the liveness check and the byte lock are those of the Bit3 buffer
(:mod:`bit3.buffer`), including its x86-64 memory-ordering argument.
"""

from controller.worldmodel.model import ACCESS_KEY_ENV, DEFAULT_ACCESS_KEY, DEFAULT_NAME, WorldModel
from controller.worldmodel.requests import UserRequest
from controller.worldmodel.segment import (
    APPLIED, FORMAT_VERSION, FREE, HEADER_FIELDS, HEADER_SIZE, MAGIC, MIN_PAYLOAD, PENDING, READ_TIMEOUT_S, REJECTED,
    REQUEST_SLOTS, SLOT_FIELDS, SLOT_HEADER, STATE_NAMES, WRITING, ModelInfo, list_segments,
)
from controller.worldmodel.spec import (
    AREAS, USER_ALWAYS, USER_AREAS, USER_MODES, USER_NEVER, USER_POWERED_DOWN, USER_WRITERS, VarSpec,
    WorldModelError, WorldModelValueError, coerce, coerce_user, default_user,
)

__all__ = [
    # variable specifications
    "AREAS", "USER_NEVER", "USER_POWERED_DOWN", "USER_ALWAYS", "USER_MODES", "USER_WRITERS", "USER_AREAS",
    "WorldModelError", "WorldModelValueError", "VarSpec", "default_user", "coerce", "coerce_user",
    # the segment format
    "MAGIC", "FORMAT_VERSION", "HEADER_SIZE", "REQUEST_SLOTS", "SLOT_HEADER", "MIN_PAYLOAD", "READ_TIMEOUT_S",
    "HEADER_FIELDS", "SLOT_FIELDS", "FREE", "WRITING", "PENDING", "APPLIED", "REJECTED", "STATE_NAMES",
    "ModelInfo", "list_segments",
    # the user-request ring
    "UserRequest",
    # the model
    "DEFAULT_ACCESS_KEY", "ACCESS_KEY_ENV", "DEFAULT_NAME", "WorldModel",
]
