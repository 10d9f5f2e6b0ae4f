"""The controller's route byte (controller/routes.py) and the driver's register table
(drivers/pio/registers.py MATRIX_SWITCHER) are two encodings of one byte on two sibling
floors (the controller may not import the drivers): they agree on every route."""

import pytest

from controller import routes
from drivers.pio import registers


@pytest.mark.parametrize("m1", range(-1, 6))
@pytest.mark.parametrize("m2", range(-1, 6))
def test_encodings_agree(m1: int, m2: int) -> None:
    try:
        driver = registers.encode_matrix_route(m1, m2)
    except ValueError as err:
        with pytest.raises(ValueError, match=str(err)):
            routes.encode_matrix_route(m1, m2)
        return
    assert routes.encode_matrix_route(m1, m2) == driver
    assert routes.decode_matrix_route(driver) == registers.decode_matrix_route(driver) == (m1, m2)


@pytest.mark.parametrize("byte", range(256))
def test_decodings_agree(byte: int) -> None:
    assert routes.decode_matrix_route(byte) == registers.decode_matrix_route(byte)


def test_tables_agree() -> None:
    fields = registers.MATRIX_SWITCHER["monitor_fields"]
    assert routes.MONITORS == tuple(fields)
    assert {m: f.lsb for m, f in fields.items()} == routes.MONITOR_SHIFT
    assert (routes.BLANK, *routes.CAMERAS) == tuple(registers.MATRIX_SWITCHER["source_codes"])
    assert routes.UNUSED_BITS == registers.MATRIX_SWITCHER["unused_bits"]
