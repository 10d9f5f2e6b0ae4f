"""The owner slots' flags (bit3/layout.py ``OWNER_FLAG_*``): CLAIMED with every claim,
SIMULATED when the claimer says its rack is the simulated one; ``HeaderInfo.rack_kind``
reads the inputs slot: simulated, real (a hardware bus) or unknown (no service)."""

from __future__ import annotations

from bit3.buffer import Bit3Buffer
from bit3.client import Client
from bit3.layout import OWNER_FLAG_CLAIMED, OWNER_FLAG_SIMULATED


def test_a_fresh_buffer_is_unknown(buf):
    assert buf.header().rack_kind == "unknown"


def test_a_simulated_claim_sets_the_flag_in_every_slot_of_the_role(buf, shm_name):
    buf.claim("service", "svc", simulated=True)
    with Client.attach(shm_name) as c:  # what another process reads
        owners = c.owners()
        for area in ("inputs", "stats", "service_messages"):
            assert owners[area].flags == OWNER_FLAG_CLAIMED | OWNER_FLAG_SIMULATED and owners[area].simulated
        assert not owners["commands"].simulated and owners["commands"].flags == 0  # nobody's
        assert c.header().rack_kind == "simulated"


def test_a_claim_on_a_hardware_bus_is_real_and_a_release_unknown(buf):
    buf.claim("service", "svc")
    o = buf.owner("inputs")
    assert o.flags == OWNER_FLAG_CLAIMED and not o.simulated
    assert buf.header().rack_kind == "real"
    buf.release()
    assert buf.owner("inputs").flags == 0 and buf.header().rack_kind == "unknown"


def test_a_new_claim_rewrites_the_flag(shm_name):
    with Bit3Buffer.create(shm_name) as b:
        b.claim("service", "simulated one", simulated=True)
        b.release()
        b.claim("service", "real one")
        assert b.header().rack_kind == "real"
