"""Orbit <-> path <-> time against the MISR Toolkit's published cases, and its own consistency."""

from __future__ import annotations

import datetime as dt

import pytest
from hypothesis import given
from hypothesis import strategies as st

from misrgraph.errors import InputError
from misrgraph.misr.orbits import (
    FIRST_ORBIT,
    ORBIT_PERIOD_DAYS,
    format_utc,
    orbit_time_range,
    orbit_to_path,
    parse_utc,
    time_to_orbit,
)

# MtkTimeToOrbitPath's cases, including both sides of the orbit 35999/36000 boundary
TIME_CASES = [
    ("2001-08-07T04:00:00Z", 8705, 123),
    ("2007-02-15T23:47:05Z", 38105, 96),
    ("2007-02-15T22:07:12Z", 38103, 64),
    ("2007-02-16T00:00:00Z", 38105, 96),
    ("2007-02-17T00:00:00Z", 38119, 87),
    ("2006-09-24T08:56:59Z", 35999, 185),
    ("2006-09-24T10:34:59Z", 35999, 185),
    ("2006-09-24T10:35:30Z", 36000, 201),
    ("2000-02-24T18:21:53Z", 996, 36),
]


def test_the_toolkit_case_inside_its_own_disagreement() -> None:
    """MtkTimeToOrbitPath puts 2006-09-24T10:35:00Z in orbit 35999, yet its orbit table starts
    orbit 36000 at JD 2454002.94097 = 10:34:59.81. Here time -> orbit inverts orbit -> time, so
    the time is in 36000; one second earlier is in 35999 (the case above)."""
    start, _ = orbit_time_range(36000)
    assert abs((start - parse_utc("2006-09-24T10:34:59.8096Z")).total_seconds()) < 0.01
    assert time_to_orbit("2006-09-24T10:35:00Z") == 36000


@pytest.mark.parametrize("time,orbit,path", TIME_CASES)
def test_time_to_orbit_and_path(time, orbit, path) -> None:
    o = time_to_orbit(time)
    assert o == orbit and int(orbit_to_path(o)) == path


@pytest.mark.parametrize(
    "orbit,start,end",
    [
        (30000, "2005-08-08T10:10:00Z", "2005-08-08T11:48:53Z"),  # MtkOrbitToTimeRange
        (996, "2000-02-24T18:11:53Z", "2000-02-24T19:50:46Z"),
    ],
)
def test_orbit_time_range(orbit, start, end) -> None:
    s, e = orbit_time_range(orbit)
    assert (format_utc(s), format_utc(e)) == (start, end)


def test_orbit_to_path_toolkit_case_and_repeat() -> None:
    assert int(orbit_to_path(12115)) == 161  # MtkOrbitToPath
    # 233 orbits later the same path; consecutive orbits step 16 paths (mod 233)
    orbits = list(range(FIRST_ORBIT, FIRST_ORBIT + 600))
    paths = orbit_to_path(orbits)
    assert all(paths[i] == paths[i + 233] for i in range(600 - 233))
    assert all((paths[i + 1] - paths[i]) % 233 == 16 for i in range(599))
    assert sorted(set(paths[:233].tolist())) == list(range(1, 234))


@given(st.integers(FIRST_ORBIT, 90000), st.floats(0.0, 0.99999))
def test_a_time_inside_an_orbit_maps_back_to_it(orbit, frac) -> None:
    s, e = orbit_time_range(orbit)
    assert abs((e - s).total_seconds() - ORBIT_PERIOD_DAYS * 86400) < 1e-3
    assert time_to_orbit(s + (e - s) * frac) == orbit


def test_time_to_orbit_inverts_the_range_at_every_thousandth_boundary() -> None:
    """Where the reference changes (the toolkit's two directions disagree there by up to 2 min)."""
    eps = dt.timedelta(milliseconds=1)
    for orbit in range(1000, 80001, 1000):
        for o in (orbit - 1, orbit):
            s, e = orbit_time_range(o)
            assert time_to_orbit(s) == o and time_to_orbit(s + eps) == o and time_to_orbit(e - eps) == o


def test_time_parsing() -> None:
    assert parse_utc("2005-08-08T12:10:00+02:00") == dt.datetime(2005, 8, 8, 10, 10, tzinfo=dt.timezone.utc)
    assert parse_utc("2005-08-08T10:10:00") == parse_utc("2005-08-08T10:10:00Z")
    assert format_utc(dt.datetime(2005, 8, 8, 10, 9, 59, 600000, tzinfo=dt.timezone.utc)) == "2005-08-08T10:10:00Z"


@pytest.mark.parametrize(
    "call,field",
    [
        (lambda: orbit_to_path(994), "orbit"),
        (lambda: orbit_to_path(1000.5), "orbit"),
        (lambda: orbit_time_range(34), "orbit"),
        (lambda: time_to_orbit("1999-08-07T04:00:00Z"), "time"),
        (lambda: time_to_orbit("2001-08-07 4 o'clock"), "time"),
    ],
)
def test_bad_input_names_the_field(call, field) -> None:
    with pytest.raises(InputError, match=field):
        call()
