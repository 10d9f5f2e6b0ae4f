"""The rack file's optional ``[amplifier_enable]`` (issue 28 item 5): absent in the seed's
rack, present in examples/rack-chargepump.toml, refused with file and line when it names
something that cannot be the charge pump's output."""

from __future__ import annotations

from pathlib import Path

import pytest

from pfma.errors import ConfigError
from pfma.rack import DEFAULT_RACK, AmplifierEnable, load_rack, parse_rack

EXAMPLE = Path(__file__).resolve().parents[2] / "examples" / "rack-chargepump.toml"


def test_the_seed_rack_has_none_and_the_example_names_its_bit():
    assert load_rack().amplifier_enable is None
    rack = load_rack(EXAMPLE)
    assert rack.amplifier_enable == AmplifierEnable("pio_video", 1, 0)
    assert rack.channel("amplifier_enable_pump").direction == "out"
    # the example is the default rack but for that section and that channel
    assert [c.signal for c in rack.channels() if c.signal != "amplifier_enable_pump"] == \
        [c.signal for c in load_rack().channels() if c.signal != "pio_video_spare_1"]


def _with(section: str) -> str:
    text = DEFAULT_RACK.read_text()
    text = text.replace('{ ch = 1, signal = "pio_video_spare_1",     label = "Spare",                     '
                        'units = "bits", direction = "in", spare = true }',
                        '{ ch = 1, signal = "pump", label = "pump", units = "bits", direction = "out" }')
    return section + "\n" + text


@pytest.mark.parametrize("section, says", [
    ('[amplifier_enable]\nboard = "pio_user"\nport = 2\nbit = 0', "pio_user port 2 (optomux_port_a) must be an output"),
    ('[amplifier_enable]\nboard = "pio_video"\nport = 0\nbit = 0', "(matrix_switcher_route) must be an output of its own"),
    ('[amplifier_enable]\nboard = "dac"\nport = 1\nbit = 0', "board 'dac' is not a pio board of this rack; pio boards: "
                                                            "pio_user, pio_video"),
    ('[amplifier_enable]\nboard = "pio_video"\nport = 1\nbit = 8', "bit must be an integer 0..7, not 8"),
    ('[amplifier_enable]\nboard = "pio_video"\nport = 4\nbit = 0', "port must be an integer 0..3, not 4"),
    ('[amplifier_enable]\nboard = "pio_video"\nport = 1', "needs bit"),
    ('[amplifier_enable]\nboard = "pio_video"\nport = 1\nbit = 0\nlevel = 1', "unknown key(s) level"),
])
def test_what_cannot_be_the_pump_is_refused_naming_the_line(section, says):
    with pytest.raises(ConfigError) as e:
        parse_rack(_with(section), "rack.toml")
    assert str(e.value).startswith("rack.toml:") and says in str(e.value)


def test_a_spare_output_port_is_accepted():
    rack = parse_rack(_with('[amplifier_enable]\nboard = "pio_video"\nport = 1\nbit = 7'), "rack.toml")
    assert rack.amplifier_enable is not None and rack.amplifier_enable.describe() == "pio_video port 1 bit 7"
