"""Attaching to a live service's Bit3 buffer, waiting for it, noticing its restart."""

from __future__ import annotations

import time
from typing import Callable

from bit3.client import Client
from bit3.layout import Layout, ServiceState

def service_status(name: str, layout: Layout | None = None) -> tuple[Client | None, str]:
    """``(client, "")`` when a live service publishes on buffer ``name``, else
    ``(None, why)``. Layout mismatches raise (they do not go away by waiting).

    Live means: the buffer exists, its layout matches, the inputs owner's process is
    running and the service state is not STOPPED.
    """
    from bit3.buffer import Bit3Error, LayoutMismatchError
    try:
        c = Client.attach(name, layout=layout)
    except LayoutMismatchError:
        raise
    except Bit3Error as err:
        return None, f"no buffer ({err})" if "no Bit3 buffer" not in str(err) else "no buffer yet"
    except (OSError, ValueError) as err:
        return None, f"buffer not readable yet ({err})"
    try:
        owner = c.buffer.owner("inputs")
        if owner.pid <= 0:
            why = "buffer exists but no service owns it (not started yet, or stopped)"
        elif not owner.alive:
            why = f"buffer exists but its service (pid {owner.pid}) is not running"
        elif c.service_state == ServiceState.STOPPED:
            why = f"service pid {owner.pid} has stopped"
        else:
            return c, ""
    except Exception as err:  # noqa: BLE001 - half-initialised buffer
        why = f"buffer not ready ({err})"
    c.close()
    return None, why


def wait_for_service(name: str, layout: Layout | None = None, *,
                     timeout_s: float | None = None, poll_s: float = 0.2,
                     say: Callable[[str], None] = print,
                     stop: Callable[[], bool] = lambda: False,
                     remind_every_s: float = 10.0) -> Client | None:
    """Attach to a live service on ``/dev/shm/NAME``, waiting (with a clear message, then a
    reminder every ``remind_every_s``) while there is none. Returns None on time-out or
    when ``stop()`` turns true; raises LayoutMismatchError for a buffer of another layout."""
    t0 = time.monotonic()
    said = ""
    last_say = t0
    while True:
        c, why = service_status(name, layout)
        if c is not None:
            if said:
                say(f"service on /dev/shm/{name} is up (after {time.monotonic() - t0:.1f} s)")
            return c
        now = time.monotonic()
        if why != said:
            say(f"waiting for service on /dev/shm/{name} ... ({why}; Ctrl-C gives up)")
            said, last_say = why, now
        elif now - last_say >= remind_every_s:
            say(f"still waiting for service on /dev/shm/{name} ({now - t0:.0f} s; {why})")
            last_say = now
        if stop() or (timeout_s is not None and now - t0 >= timeout_s):
            return None
        time.sleep(poll_s)


def buffer_replaced(client: Client) -> bool:
    """The name now refers to another segment than the one ``client`` maps (the service
    was restarted and created a new buffer), or the name is gone."""
    try:
        from bit3.buffer import Bit3Buffer
        b = Bit3Buffer.attach(client.buffer.name, readonly=True, layout=client.layout)
    except Exception:  # noqa: BLE001 - gone or different: either way not ours any more
        return True
    try:
        return b.header().created_ns != client.header().created_ns
    finally:
        b.close()
