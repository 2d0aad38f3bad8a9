"""Serial line protocol: checksum, header and sample lines (tacest.sensors.serial_protocol)."""

import math

import numpy as np
import pytest

from tacest.sensors.serial_protocol import (
    NORMAL_NORM_TOL,
    Header,
    LineError,
    Precision,
    checksum,
    format_header,
    format_sample,
    parse_header,
    parse_sample,
    with_checksum,
)

H2 = Header(dim=2, fingers=1, radius=(0.01,), dt=0.01, gravity=(0.0, -9.81))
H3 = Header(dim=3, fingers=2, radius=(0.01, 0.012), dt=0.001, gravity=(0.0, 0.0, -9.81))

# A 2-D line: seq 7, t 0.07 s, finger 0 at (0.1, 0.05) m, in contact, force (0.5, -0.2) N,
# normal (0, 1).
LINE_BODY = b"S,7,0.07,0,0.1,0.05,1,0.5,-0.2,0,1"
# Checksum by hand: XOR is associative and a byte XORed with itself is 0, so only the
# characters that occur an odd number of times survive.  Counts in LINE_BODY:
#   ','x10  '0'x9  '.'x5  '1'x3  '5'x2  '7'x2  'S'x1  '-'x1  '2'x1
# odd: 'S' 0x53, '0' 0x30, '.' 0x2E, '1' 0x31, '-' 0x2D, '2' 0x32
#   0x53 ^ 0x30 = 0x63;  ^ 0x2E = 0x4D;  ^ 0x31 = 0x7C;  ^ 0x2D = 0x51;  ^ 0x32 = 0x63
LINE_CS = 0x63


def test_checksum_of_known_line_by_hand():
    assert checksum(LINE_BODY) == LINE_CS
    assert with_checksum(LINE_BODY.decode()) == LINE_BODY.decode() + "*63"
    assert checksum(b"") == 0


def test_parse_valid_2d_line():
    s = parse_sample(LINE_BODY + b"*63", H2)
    assert (s.seq, s.t, s.finger, s.contact) == (7, 0.07, 0, 1)
    assert s.position == (0.1, 0.05)
    assert s.force == (0.5, -0.2)
    assert s.normal == (0.0, 1.0)
    # lower-case hex is accepted too
    assert parse_sample(LINE_BODY + b"*63".lower(), H2).seq == 7


def test_parse_valid_3d_line_and_renormalise():
    # 3-D, finger 1; normal rounded to 3 decimals: |n| = 1.00002, within tolerance
    body = "S,12,1.5,1,0.1,0.2,0.3,1,0.0,0.0,-2.0,0.577,0.577,0.577"
    s = parse_sample(with_checksum(body).encode(), H3)
    assert s.seq == 12 and s.finger == 1 and s.contact == 1
    assert s.position == (0.1, 0.2, 0.3)
    assert s.force == (0.0, 0.0, -2.0)
    # renormalised exactly (to float rounding, 1e-12)
    assert abs(math.sqrt(sum(x * x for x in s.normal)) - 1.0) < 1e-12
    np.testing.assert_allclose(s.normal, [3 ** -0.5] * 3, atol=1e-3)  # 1e-3: the 3-decimal rounding


def test_no_contact_normal_is_nan_whether_empty_or_given():
    for nfields in (",,", ",nan,nan", ",0.3,0.1"):
        body = "S,1,0.01,0,0.1,0.05,0,0,0" + nfields
        s = parse_sample(with_checksum(body).encode(), H2)
        assert s.contact == 0 and all(math.isnan(x) for x in s.normal)


@pytest.mark.parametrize("body,reason", [
    ("S,1,0.01,0,0.1,0.05,0,0,0,,,", "fields"),            # one field too many
    ("S,1,0.01,0,0.1,0.05,0,0,0,", "fields"),               # one too few
    ("S,1,0.01,0,0.1,0.05,0,0,0,,,,,", "fields"),           # a 3-D line under a 2-D header
    ("S,x,0.01,0,0.1,0.05,0,0,0,,", "number"),              # seq not an integer
    ("S,-1,0.01,0,0.1,0.05,0,0,0,,", "number"),             # negative seq
    ("S,1,abc,0,0.1,0.05,0,0,0,,", "number"),               # clock unparsable
    ("S,1,0.01,0,0.1,1e,0,0,0,,", "number"),                # position unparsable
    ("S,1,0.01,0,nan,0.05,0,0,0,,", "number"),              # position NaN
    ("S,1,0.01,0,0.1,inf,0,0,0,,", "number"),               # position inf
    ("S,1,0.01,0,0.1,0.05,2,0,0,,", "number"),              # contact not 0/1
    ("S,1,0.01,0,0.1,0.05,0,,0,,", "number"),               # force empty though header says force
    ("S,1,0.01,1,0.1,0.05,0,0,0,,", "finger"),              # finger 1 of 1
    ("S,1,0.01,0,0.1,0.05,1,0,0,,", "normal"),              # contact without normal
    ("S,1,0.01,0,0.1,0.05,1,0,0,nan,nan", "normal"),        # contact with NaN normal
    ("S,1,0.01,0,0.1,0.05,1,0,0,0,1.06", "normal"),         # |n| = 1.06 > 1 + 5 %
    ("X,1,0.01,0,0.1,0.05,0,0,0,,", "malformed"),           # unknown line type
])
def test_invalid_lines_have_reasons(body, reason):
    with pytest.raises(LineError) as exc:
        parse_sample(with_checksum(body).encode(), H2)
    assert exc.value.reason == reason


def test_normal_tolerance_edge():
    # |n| = 1.04 is inside the 5 % tolerance and is renormalised; 1.06 is not (above)
    ok = parse_sample(with_checksum("S,1,0,0,0.1,0.05,1,0,0,0,1.04").encode(), H2)
    assert ok.normal == (0.0, 1.0)
    assert NORMAL_NORM_TOL == 0.05


def test_bad_checksum_truncated_and_non_ascii():
    good = with_checksum("S,1,0.01,0,0.1,0.05,0,0,0,,").encode()
    with pytest.raises(LineError) as e:
        parse_sample(good[:-2] + b"00", H2)
    assert e.value.reason == "checksum"
    with pytest.raises(LineError) as e:
        parse_sample(good[:15], H2)  # truncated: no *CS
    assert e.value.reason == "malformed"
    with pytest.raises(LineError) as e:
        parse_sample(good[:-1], H2)  # one hex digit
    assert e.value.reason == "malformed"
    bad = b"S,1,0.01,0,0.1,0.05,0,0,0,,\xff"
    with pytest.raises(LineError) as e:
        parse_sample(bad + b"*%02X" % checksum(bad), H2)  # checksum right, bytes not ASCII
    assert e.value.reason == "malformed"


def test_empty_clock_is_nan():
    s = parse_sample(with_checksum("S,1,,0,0.1,0.05,0,0,0,,").encode(), H2)
    assert math.isnan(s.t)


def test_force_free_header_ignores_force_fields():
    h = parse_header(b"#TACEST,1,dim=2,fingers=1,radius=0.01,dt=0.01,force=0")
    assert not h.force
    s = parse_sample(with_checksum("S,1,0.01,0,0.1,0.05,0,,,,").encode(), h)
    assert all(math.isnan(x) for x in s.force)


def test_parse_header_spec_example_and_liberal_forms():
    h = parse_header(b"#TACEST,1,dim=2,fingers=1,radius=0.010,dt=0.01")
    assert (h.dim, h.fingers, h.radius, h.dt, h.force, h.gravity) == (2, 1, (0.01,), 0.01, True, (0.0, -9.81))
    for text in (b"#TACEST,1,dim=3,fingers=2,radius=0.01;0.012,dt=0.001",
                 b"#TACEST,1,dim=3,fingers=2,radius=0.01|0.012,dt=0.001",
                 b"#TACEST,1,dim=3,fingers=2,radius=[0.01,0.012],dt=0.001",
                 b"#tacest, 1, DIM=3, Radius=0.01 0.012, dt=0.001, fw=2.1",  # fingers from the radii
                 with_checksum("#TACEST,1,dim=3,fingers=2,radius=0.01;0.012,dt=0.001").encode()):
        h = parse_header(text)
        assert (h.dim, h.fingers, h.radius, h.dt) == (3, 2, (0.01, 0.012), 0.001), text
    h = parse_header(b"#TACEST,1,dim=3,fingers=3,radius=0.01,dt=0.001,fw=2.1")
    assert h.radius == (0.01,) * 3 and h.extras == {"fw": "2.1"}


@pytest.mark.parametrize("text,reason", [
    (b"#TACEST,2,dim=2,fingers=1,radius=0.01,dt=0.01", "header"),   # unknown version
    (b"#TACEST,1,dim=4,fingers=1,radius=0.01,dt=0.01", "header"),
    (b"#TACEST,1,dim=2,fingers=2,radius=0.01;0.01;0.01,dt=0.01", "header"),
    (b"#TACEST,1,dim=2,fingers=1,radius=-0.01,dt=0.01", "header"),
    (b"#TACEST,1,dim=2,fingers=1,radius=0.01", "header"),            # no dt
    (b"#TACEST,1,dim=2,fingers=1,radius=0.01,dt=0", "header"),
    (b"#TACEST,1,dim=2,fingers=1,radius=0.01,dt=0.01*00", "checksum"),
])
def test_bad_headers(text, reason):
    with pytest.raises(LineError) as exc:
        parse_header(text)
    assert exc.value.reason == reason


def test_format_parse_round_trip_and_header_round_trip():
    for h in (H2, H3, Header(dim=2, fingers=1, radius=(0.02,), dt=0.005, force=False, gravity=(0.0, -1.62))):
        again = parse_header(format_header(h).encode())
        assert again.same_settings(h)
        assert parse_header(format_header(h, checksum_suffix=True).encode()).same_settings(h)
    line = format_sample(5, 0.05, 1, [0.1234567, -0.2, 0.3], 1, [1.23456, 0, -1], [0, 0.6, 0.8]).encode()
    s = parse_sample(line, H3)
    p = Precision()
    # tolerances: half a unit in the last printed decimal of each field
    np.testing.assert_allclose(s.position, [0.1234567, -0.2, 0.3], atol=0.5 * 10.0 ** -p.position)
    np.testing.assert_allclose(s.force, [1.23456, 0, -1], atol=0.5 * 10.0 ** -p.force)
    np.testing.assert_allclose(s.normal, [0, 0.6, 0.8], atol=1e-12)  # exact decimals, renormalised
