"""docs/python.md's ten-line script, run as written against `pfma serve` (real time).

The only change made to the script is the buffer name: a private one, so the test never
touches a user's service. The keep-alive is a real thread here, on the real clock; the
rules it enforces are tested in simulated time in test_handle.py.
"""

from __future__ import annotations

import re
import subprocess
import sys
import time
import uuid
from pathlib import Path

import pytest

from bit3.buffer import Bit3Buffer
from bit3.client import Client
from bit3.layout import ServiceState
from bit3.ring import FrameRing

pytestmark = pytest.mark.realtime

REPO = Path(__file__).resolve().parents[2]
DOC = REPO / "docs" / "python.md"


def _script() -> str:
    """The first ``python`` block of docs/python.md: the ten-line script."""
    m = re.search(r"```python\n(.*?)```", DOC.read_text(), re.S)
    assert m, "docs/python.md has no python block"
    return m.group(1)


def _serve(name: str) -> subprocess.Popen:
    p = subprocess.Popen([sys.executable, "-m", "tools.cli", "serve", "--buffer", name, "--duration", "60"],
                         cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    assert p.stdout is not None
    seen = []
    for line in p.stdout:  # bounded by the service's --duration
        seen.append(line)
        if "Ctrl-C stops" in line:
            return p
    raise AssertionError("pfma serve did not start: " + "".join(seen))


def _run(code: str, tmp_path: Path) -> subprocess.CompletedProcess:
    f = tmp_path / "script.py"
    f.write_text(code)
    return subprocess.run([sys.executable, str(f)], cwd=REPO, capture_output=True, text=True, timeout=60)


@pytest.fixture
def service():
    name = "pfma-py-" + uuid.uuid4().hex[:8]
    p = _serve(name)
    try:
        with Client.attach(name) as c:
            for _ in range(10_000):  # a bound, not a timing: until the first frames are published
                if c.read_inputs().frame > 10:
                    break
                time.sleep(0.001)
        yield name
    finally:
        p.terminate()
        p.wait(30)
        Bit3Buffer.unlink(name)
        FrameRing.unlink(name)
        Path(f"/dev/shm/{name}.faults").unlink(missing_ok=True)


def test_the_documented_script_runs_moves_the_elbow_and_leaves_the_service_safe(service, tmp_path):
    script = _script()
    assert len(script.strip().splitlines()) <= 10 and 'Rack.open("pfma")' in script
    with Client.attach(service) as c:
        before = c.read_inputs().elbow_pitch_angle
        out = _run(script.replace('Rack.open("pfma")', f'Rack.open("{service}")'), tmp_path)
        assert out.returncode == 0, out.stderr
        assert re.fullmatch(r"ARMED elbow_pitch_angle = [-\d.]+ rad \(ok\) elbow_pitch_rate = [-\d.]+ rad/s \(ok\)\n",
                            out.stdout), out.stdout
        after = float(out.stdout.split()[3])
        assert after - before < -0.03  # -0.1 rad/s for a second moved the elbow down
        assert c.service_state is ServiceState.SAFE  # disarmed by the script's end, not tripped
        texts = [m.text for m in c.messages(0)]
        assert "disarmed by command" in texts and not any("stale heartbeat" in t for t in texts), texts


def test_a_script_that_stops_renewing_its_rates_stops_the_arm_and_stays_armed(service, tmp_path):
    code = (f"import time\nfrom bit3.handle import Rack\n"
            f"with Rack.open({service!r}) as rack:\n"
            f"    rack.arm(current_limit_a=2.0)\n"
            f"    rack.rates(elbow_pitch=-0.1)\n"
            f"    time.sleep(1.0)  # hung: no renewal\n"
            f"    cmd = rack.client.read_commands().joint_rate_rad_s\n"
            f"    print(rack.expired, rack.state.name, float(abs(cmd).max()))\n")
    out = _run(code, tmp_path)
    assert out.returncode == 0, out.stderr
    assert out.stdout == "1 ARMED 0.0\n", (out.stdout, out.stderr)
    assert out.stderr.count("rate command expired after 0.3 s") == 1, out.stderr


def test_no_service_is_one_line(tmp_path):
    out = _run("from bit3.handle import Rack\nRack.open('pfma-none-" + uuid.uuid4().hex[:6] + "')\n", tmp_path)
    assert out.returncode != 0
    last = out.stderr.strip().splitlines()[-1]
    assert last.startswith("bit3.handle.RackError: no I/O service runs on buffer"), out.stderr


def test_a_script_without_with_that_ends_disarms_instead_of_tripping(service, tmp_path):
    code = (f"from bit3.handle import Rack\n"
            f"rack = Rack.open({service!r})\n"
            f"rack.arm(current_limit_a=2.0)\n"
            f"print(rack.state)\n")  # no close(), no with: the process just ends
    out = _run(code, tmp_path)
    assert out.returncode == 0 and out.stdout == "ARMED\n", (out.stdout, out.stderr)
    with Client.attach(service) as c:
        texts = [m.text for m in c.messages(0)]
        armed = max(i for i, t in enumerate(texts) if t == "armed")
        after = texts[armed + 1:]  # host stall notices of a loaded machine may come in between
        assert "disarmed by command" in after and not any("stale heartbeat" in t for t in after), texts
        assert c.service_state is ServiceState.SAFE
