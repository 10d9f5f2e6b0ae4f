"""`pfma checkout`'s matrix group on the fake switcher (issue 18 item 4, docs/cameras.md):
every route of the switch-to-route table, named in words, written with the strobe handshake
and read back as applied by the service; a switcher that does not acknowledge fails the
route naming it, with the service's one message."""

from controller.routes import ALL_ROUTES, route_text
from tools.checkout import FAIL, PASS, Checkout


def _run(target, cfg, **kw):
    lines: list[str] = []
    rep = Checkout(target, cfg, say=lines.append, only=["matrix"], **kw).run()
    return rep, lines


def test_every_route_checked_by_name_on_the_fake_switcher(sim, cfg):
    switcher = sim.world.bus["pio_video"].switcher
    before = int(sim.inputs().matrix_route)
    rep, _ = _run(sim, cfg)
    rows = [r for r in rep.results if r.group == "matrix"]
    routes = [r for r in rows if r.check.startswith("route ")]
    # the service writes only a change: the group starts after the route applied now (blank, blank)
    assert before == ALL_ROUTES[0]
    assert [r.check for r in routes] == [f"route {route_text(x)}" for x in ALL_ROUTES[1:] + ALL_ROUTES[:1]]
    assert len(routes) == 16 and all(r.status == PASS for r in rows)
    assert "route monitor 1: camera 2, monitor 2: camera 3" in [r.check for r in routes]
    assert "route monitor 1: blank, monitor 2: blank" in [r.check for r in routes]
    # the configured port-line patterns that are not routes follow as their own rows
    assert [r.check for r in rows[16:]] == ["port lines 0x10", "port lines 0x20", "port lines 0x40",
                                            "port lines 0x80", "port lines 0x55", "port lines 0xAA"]
    # each row saw the fake switcher latch its byte after a strobe and acknowledge it
    assert all("1 acknowledge(s)" in r.detail for r in rows)
    assert switcher.acks >= len(rows)
    # the route from before the group is put back
    sim.wait(0.1)
    assert int(sim.inputs().matrix_route) == before == switcher.route


def test_silent_switcher_fails_the_first_route_naming_it(sim, cfg):
    sim.wait(0.1)  # the service has applied its first route (blank, blank)
    sim.world.bus["pio_video"].inject("switcher_silent")
    rep, _ = _run(sim, cfg)
    f = rep.failures()[0]
    assert f.status == FAIL and f.group == "matrix"
    assert f.check == f"route {route_text(ALL_ROUTES[1])}"  # the first route after the one applied now
    # the service's one message (cut to the Bit3 queue's 56 bytes) and the fake's view
    assert "not applied within 0.5 s: pio_video: matrix route 0x04 failed" in f.detail
    assert "fake switcher latched 0x04, 0 acknowledge(s)" in f.detail
