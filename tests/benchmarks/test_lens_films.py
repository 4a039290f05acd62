"""The lens-film benchmark (:mod:`benchmarks.lens_films`) renders what it says it compares: one
film size a lens unpadded, the padded films shared, and the module's step restored after."""

from __future__ import annotations

from benchmarks.lens_films import render_times
from services.renderer import free_view


def test_padded_lenses_share_a_film_and_the_step_is_restored():
    step = free_view.FILM_STEP_PX
    unpadded = render_times("demo", [-0.05, -0.06], repeat=1, step=1)
    padded = render_times("demo", [-0.05, -0.06], repeat=1, step=step)
    assert len(unpadded["films"]) == 2
    assert len(padded["films"]) == 1
    assert len(unpadded["times"]) == len(padded["times"]) == 2
    assert free_view.FILM_STEP_PX == step
