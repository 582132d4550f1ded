"""Every shipped scene writes the same results, to the byte, as when its digests were stored.

The guard of changes that must not change behaviour (restructuring, renaming, documentation):
CSVs, units, the wall's VTU files and the summary without its clock fields. A change meant to
change results regenerates the digests (`tests/scene_digests.py --update`) and says why.
"""

from __future__ import annotations

import json

import pytest

from scene_digests import STORED, scene_digests, shipped_scenes

STORED_DIGESTS = json.loads(STORED.read_text())


def test_every_shipped_scene_has_stored_digests():
    assert sorted(STORED_DIGESTS) == shipped_scenes()


@pytest.mark.parametrize("name", shipped_scenes())
def test_shipped_scene_results_are_byte_identical(name, tmp_path):
    digests = scene_digests(name, tmp_path)
    stored = STORED_DIGESTS[name]
    assert sorted(digests) == sorted(stored), "the run wrote other files than the stored run"
    changed = [path for path in stored if digests[path] != stored[path]]
    assert not changed, f"{name}: results changed in {changed}"
