"""RerunLogger.log_people and log_event: each identity in its own colour with its id as
label, births and deaths as text events, read back from the .rrd."""

from __future__ import annotations

import numpy as np
from test_viz import read_rrd

from cpf_jax.viz import RerunLogger, identity_colour


def test_people_and_events_round_trip(tmp_path):
    path = tmp_path / "people.rrd"
    with RerunLogger(path, raw=True, blueprint=None) as log:
        log.log_people(0, [3, 7], [[1, 2, 10, 20], [30, 5, 8, 16]])
        log.log_event(0, "id 3 born")
        log.log_people(1, [], np.zeros((0, 4)))
        log.log_event(1, "id 7 died", level="WARN")
    rrd = read_rrd(str(path))
    people = rrd["/world/camera/people"]
    first = [r for r in people["rows"] if r["frame"] == 0 and r.get("Boxes2D:labels") is not None]
    assert first and list(first[0]["Boxes2D:labels"]) == ["id 3", "id 7"]
    colours = list(first[0]["Boxes2D:colors"])
    assert len(set(colours)) == 2
    assert 1 in people["frames"]  # no one: the entity is cleared
    events = rrd["/events"]["rows"]
    texts = {(r["frame"], str(r["TextLog:text"][0])) for r in events}
    assert (0, "id 3 born") in texts and (1, "id 7 died") in texts


def test_identity_colours_differ_for_neighbouring_ids():
    colours = [identity_colour(i) for i in range(1, 9)]
    assert len(set(colours)) == 8
    assert all(0 <= c <= 255 for rgb in colours for c in rgb)
    assert identity_colour(3) == identity_colour(3)
