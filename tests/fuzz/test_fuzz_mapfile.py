"""Saved maps with a valid checksum and mutated content, through the daemon's resume path.

Start from a real map (a pipeline's state after ``sim://`` frames, made once per session), mutate
its content (drop keys, change types, dtypes and shapes, put NaN, inf, huge or negative values in,
truncate arrays, forge packed-array headers), seal it with a valid checksum, resume from it as the
daemon does (``MapFileOutput.resume``) and step the pipeline. The outcome is one of two: a clean
refusal (one log line; the file moved aside under a new name, or, for a valid map of another
configuration, left for ``persistence.keep_maps``), or a working filter that steps, publishes and
saves. Any other exception fails the test. ``ROBOTD_FUZZ_EXAMPLES`` runs more examples.
"""

from __future__ import annotations

import os

from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from tests.fuzz.targets import MAP_VARIANTS, Drawn, mutate_map, mutate_map_values, resume_and_run
from tests.support import saved_maps

MAX_EXAMPLES = int(os.environ.get("ROBOTD_FUZZ_EXAMPLES", "60"))
VARIANTS = MAP_VARIANTS


@settings(max_examples=MAX_EXAMPLES, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(variant=st.sampled_from(VARIANTS), n=st.integers(1, 3), data=st.data())
def test_a_mutated_map_is_refused_cleanly_or_runs(variant: tuple[str, int], n: int, data: st.DataObject) -> None:
    state = saved_maps.saved_state(*variant)
    for _ in range(n):
        mutate_map(state, variant, Drawn(data.draw))
    resume_and_run(saved_maps.seal(state), variant)


@settings(max_examples=MAX_EXAMPLES, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(variant=st.sampled_from(VARIANTS), n=st.integers(1, 3), data=st.data())
def test_a_map_with_odd_values_is_refused_cleanly_or_runs(
    variant: tuple[str, int], n: int, data: st.DataObject
) -> None:
    # the structure kept, the values changed: most of these maps load, and the filter must run
    state = saved_maps.saved_state(*variant)
    for _ in range(n):
        mutate_map_values(state, variant, Drawn(data.draw))
    resume_and_run(saved_maps.seal(state), variant)


def test_the_unmutated_map_resumes() -> None:
    # the property's baseline: without a mutation every variant loads and runs
    for variant in VARIANTS:
        assert resume_and_run(saved_maps.seal(saved_maps.saved_state(*variant)), variant) == "resumed", variant
