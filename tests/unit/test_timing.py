"""Line timing (Modbus over Serial Line v1.02, 2.5.1.1): t1.5 and t3.5 from the line settings.

A character is start + data + parity + stop bits: 8N1 is 10 bits, 8E1 and 8N2 are 11
(the specification's nominal RTU character), 8E2 is 12. Above 19200 baud the
specification fixes t1.5 = 750 us and t3.5 = 1750 us.
"""

from __future__ import annotations

import pytest

from gateway.core.timing import (
    bits_per_character,
    character_time,
    t15,
    t35,
    transmission_time,
)


def approx(value: float) -> object:
    return pytest.approx(value, rel=1e-12, abs=0.0)


@pytest.mark.parametrize(
    ("data_bits", "parity", "stop_bits", "bits"),
    [
        (8, "N", 1, 10),
        (8, "E", 1, 11),
        (8, "O", 1, 11),
        (8, "N", 2, 11),
        (8, "E", 2, 12),
        (7, "E", 1, 10),
        (7, "N", 2, 10),
        (8, "e", 1, 11),  # lower-case parity letters as pyserial spells them
        (8, "n", 1, 10),
        (8, "M", 1, 11),
        (8, "S", 1, 11),
        (8, "N", 1.5, 10.5),
    ],
)
def test_bits_per_character(data_bits: int, parity: str, stop_bits: float, bits: float) -> None:
    assert bits_per_character(data_bits, parity, stop_bits) == bits


def test_default_line_is_8n1() -> None:
    assert bits_per_character() == 10
    assert character_time(9600) == approx(10 / 9600)


@pytest.mark.parametrize(
    ("baudrate", "parity", "stop_bits", "bits"),
    [
        (1200, "N", 1, 10),
        (2400, "N", 1, 10),
        (4800, "E", 1, 11),
        (9600, "N", 1, 10),
        (9600, "E", 1, 11),
        (9600, "O", 1, 11),
        (9600, "N", 2, 11),
        (9600, "E", 2, 12),
        (19200, "N", 1, 10),
        (19200, "E", 1, 11),
        (19200, "N", 2, 11),
        (19200, "E", 2, 12),
    ],
)
def test_character_timing_up_to_19200(
    baudrate: int, parity: str, stop_bits: float, bits: int
) -> None:
    assert character_time(baudrate, 8, parity, stop_bits) == approx(bits / baudrate)
    assert t15(baudrate, 8, parity, stop_bits) == approx(1.5 * bits / baudrate)
    assert t35(baudrate, 8, parity, stop_bits) == approx(3.5 * bits / baudrate)


def test_literal_values_at_9600_and_19200() -> None:
    assert t15(9600) == approx(0.0015625)  # 1.5 x 10 bits / 9600
    assert t35(9600) == approx(0.003645833333333333)
    assert t35(9600, 8, "E", 1) == approx(0.004010416666666667)  # 3.5 x 11 / 9600
    assert t15(19200) == approx(0.00078125)
    assert t35(19200) == approx(0.0018229166666666667)
    assert t35(19200, 8, "E", 1) == approx(0.0020052083333333334)


@pytest.mark.parametrize("baudrate", [19201, 38400, 57600, 115200, 230400, 921600])
@pytest.mark.parametrize(("parity", "stop_bits"), [("N", 1), ("E", 1), ("N", 2), ("E", 2)])
def test_fixed_timing_above_19200(baudrate: int, parity: str, stop_bits: float) -> None:
    assert t15(baudrate, 8, parity, stop_bits) == 0.000750
    assert t35(baudrate, 8, parity, stop_bits) == 0.001750


def test_character_time_is_not_fixed_above_19200() -> None:
    assert character_time(115200) == approx(10 / 115200)
    assert character_time(38400, 8, "E", 1) == approx(11 / 38400)


def test_t35_is_longer_than_t15() -> None:
    for baudrate in (1200, 9600, 19200, 38400, 115200):
        assert t35(baudrate) > t15(baudrate)


def test_transmission_time() -> None:
    assert transmission_time(8, 9600) == approx(80 / 9600)
    assert transmission_time(256, 19200, 8, "E", 1) == approx(256 * 11 / 19200)
    assert transmission_time(0, 9600) == 0
