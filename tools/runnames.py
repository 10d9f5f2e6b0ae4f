"""The names ``make run``'s system takes: the buffer ``pfma`` and the world model ``pfma_wm``,
the defaults every other tool reads (``pfma read``, ``stats``, ``monitor``, ``fault``,
``wm``, ``console`` ...), so the README's *(service)* lines work beside it as written.

Assumed (docs/console.md "Names"): a name is in use when a live process owns it, by the
rule each owner already keeps: a Bit3 buffer whose service holds its claim lock
(:meth:`bit3.buffer.Bit3Buffer.owner_alive`), a world model whose owner's pid runs
(:meth:`controller.worldmodel.WorldModel.info`). A leftover of a crashed or killed run (its
owner gone) is not in use: the buffer is removed here and the default taken (the world
model, the frame ring and the fault socket are replaced by their own creators).

When either default is in use, ``make run`` does not stop: it takes a private pair
(``pfma-sim-XXXXXXXX`` and ``pfma-sim-XXXXXXXX_wm``, one pair so no tool pairs our buffer
with another system's world model) and says so in one line naming them and the options
that reach them. A name given explicitly (``--buffer``, ``--wm``) is not replaced: in use,
it is refused in one line.
"""

from __future__ import annotations

import uuid
from dataclasses import dataclass

from bit3.buffer import Bit3Buffer
from pfma.errors import PfmaError

#: the names every tool reads by default
DEFAULT_BUFFER, DEFAULT_WM = "pfma", "pfma_wm"
#: the private buffer's prefix (its world model: the buffer's name + ``_wm``)
PRIVATE_PREFIX = "pfma-sim-"


@dataclass(frozen=True)
class RunNames:
    """The names a run takes, and the one line saying why they are not the ones asked for."""

    buffer: str
    wm: str | None
    note: str | None = None  #: None: the names asked for

    @property
    def private(self) -> bool:
        return self.note is not None

    def reach(self) -> str:
        """The options that reach these names from another tool (``--buffer X --wm Y``)."""
        return f"--buffer {self.buffer}" + (f" --wm {self.wm}" if self.wm else "")

    def describe(self) -> str:
        """``buffer 'pfma', world model 'pfma_wm'``: what a screen shows."""
        return f"buffer {self.buffer!r}" + (f", world model {self.wm!r}" if self.wm else "")


def buffer_in_use(name: str) -> str | None:
    """Why Bit3 buffer ``name`` is in use (its service is alive), or None (absent, or a
    leftover whose service is gone)."""
    alive, who = Bit3Buffer.owner_alive(name)
    return f"a service already runs on buffer {name!r} ({who})" if alive else None


def wm_in_use(name: str) -> str | None:
    """Why world model ``name`` is in use (its owner runs, or it cannot be read, so it cannot
    be proved unused), or None (absent, or its owner is gone)."""
    import os

    from controller.worldmodel import WorldModel
    if not os.path.exists(f"/dev/shm/{name}"):
        return None
    try:
        info = WorldModel.attach(name).close_after(lambda m: m.info())
    except PfmaError as err:
        return f"world model {name!r} exists and cannot be read ({err})"
    if info.owner_alive:
        return f"a controller already runs on world model {name!r} ({info.owner!r}, pid {info.owner_pid})"
    return None


def claim(buffer: str = DEFAULT_BUFFER, wm: str | None = DEFAULT_WM, *, fallback: bool = True) -> RunNames:
    """The names to run on: ``buffer`` and ``wm`` (None: no world model) when neither is in
    use (a leftover buffer of a dead service is removed); else, with ``fallback``, a private
    pair and the one line that says so; without, :class:`PfmaError`.

    A second run may still take the name between this check and its create: the create then
    refuses, as it always did.
    """
    why, option = buffer_in_use(buffer), "--buffer"
    if why is None and wm:
        why, option = wm_in_use(wm), "--wm"
    if why is None:
        Bit3Buffer.unlink(buffer)  # a leftover (if any): its service is gone, checked just above
        return RunNames(buffer, wm)
    if not fallback:
        raise PfmaError(f"{why}; stop it first, or name another ({option} NAME)")
    private = PRIVATE_PREFIX + uuid.uuid4().hex[:8]
    names = RunNames(private, f"{private}_wm" if wm else None)
    return RunNames(names.buffer, names.wm, f"{why}; this system runs on the private {names.describe()} "
                                            f"instead: reach it with {names.reach()}")
