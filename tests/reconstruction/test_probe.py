"""The likelihood-ratio probe along the px-pz unseen direction."""

from __future__ import annotations

import dataclasses

import pytest
import torch
from test_unseen import _beam_cov, _maps, _partial

from diffaccel.reconstruction import ReconstructionConfig
from diffaccel.reconstruction.generator import BeamGenerator
from diffaccel.reconstruction.probe import PROBE_PAIR, probe_members
from diffaccel.reconstruction.unseen import (
    PLACEMENT_PARTICLES,
    _fold,
    member_moments,
    place_unseen,
    traded_pairs,
    transport_map,
    unseen_directions,
)

CONFIG = ReconstructionConfig(dims=6, width=8, depth=2, probe_unseen=0.05)


def _placed_member(seed: int) -> dict:
    """A small generator moved to the pair prior's point of the test beam."""
    gen = BeamGenerator(
        6,
        width=8,
        depth=2,
        scale=torch.ones(6),
        generator=torch.Generator().manual_seed(seed),
    )
    state = {k: v.detach().clone() for k, v in gen.state_dict().items()}
    mu, own = member_moments(state, 6, 8, 2, PLACEMENT_PARTICLES, CONFIG.seed)
    cov = _beam_cov()
    target = place_unseen(cov, unseen_directions(_maps(), cov))
    return _fold(state, transport_map(own, target), mu)


def _cov(state: dict) -> torch.Tensor:
    return member_moments(state, 6, 8, 2, PLACEMENT_PARTICLES, CONFIG.seed)[1]


def _partial_at(state: dict, t: float) -> float:
    """px-pz partial correlation of ``state`` moved by ``t`` along px-pz."""
    cov = _cov(state)
    v = unseen_directions(_maps(), cov)
    return _partial(cov + t * v[traded_pairs(v, cov).index(PROBE_PAIR)], 1, 5)


def _probe(
    members: list[dict], best: float, weight: float, config=CONFIG
) -> tuple[list[dict], dict, list]:
    """Probe with a refit that changes nothing and a misfit that is smallest
    where the member's px-pz partial correlation is ``best``."""
    holds = []

    def refit(k, state, hold, callback):
        holds.append((k, hold))
        return state

    def score(state):
        return weight * (_partial(_cov(state), 1, 5) - best) ** 2

    out, record = probe_members(members, refit, score, config, _maps())
    return out, record, holds


def test_probe_steps_to_where_the_images_fit_better() -> None:
    members = [_placed_member(0), _placed_member(1)]
    assert abs(_partial(_cov(members[0]), 1, 5)) < 1e-3  # at the prior point
    best = _partial_at(members[0], -0.1)
    assert abs(best) > 0.02
    out, record, holds = _probe(members, best, 1.0)
    assert record["t"] == pytest.approx(-0.1)
    assert [s["t"] for s in record["steps"]] == pytest.approx([0, -0.05, 0.05, -0.1])
    gains = {s["t"]: s["mean_gain"] for s in record["steps"]}
    assert gains[-0.05] > CONFIG.probe_gain and gains[-0.1] > CONFIG.probe_gain
    assert gains[0.05] < 0
    # every member refitted at every point, its covariance held there
    assert len(holds) == 2 * 4
    k, hold = holds[2]  # member 0 at t = -0.05
    cov = _cov(members[0])
    v = unseen_directions(_maps(), cov)
    moved = cov + -0.05 * v[traded_pairs(v, cov).index(PROBE_PAIR)]
    assert k == 0
    assert torch.allclose(hold, moved, rtol=1e-6, atol=1e-6 * float(cov.abs().max()))
    # placed again at the prior point plus the chosen t
    for member in out:
        assert _partial(_cov(member), 1, 5) == pytest.approx(best, abs=0.01)


def test_probe_stops_after_probe_points() -> None:
    members = [_placed_member(0)]
    best = _partial_at(members[0], -0.1)
    config = ReconstructionConfig(
        dims=6, width=8, depth=2, probe_unseen=0.05, probe_points=1
    )
    _, record, holds = _probe(members, best, 1.0, config)
    assert record["t"] == pytest.approx(-0.05)
    assert len(holds) == 3


@pytest.mark.parametrize("where, weight", [("prior", 1.0), ("off", 1e-4)])
def test_probe_stays_at_the_prior_without_a_clear_gain(
    where: str, weight: float
) -> None:
    members = [_placed_member(0), _placed_member(1)]
    # the misfit is smallest at the prior point, or off it by too little
    best = 0.0 if where == "prior" else _partial_at(members[0], -0.1)
    out, record, holds = _probe(members, best, weight)
    assert record["t"] == 0.0
    assert len(holds) == 2 * 3
    gains = [s["mean_gain"] for s in record["steps"][1:]]
    assert max(gains) <= CONFIG.probe_gain
    for member in out:
        assert abs(_partial(_cov(member), 1, 5)) < 2e-3


@pytest.mark.parametrize(
    "field, value",
    [
        ("probe_unseen", -0.05),
        ("probe_unseen", 1.5),
        ("probe_gain", float("nan")),
        ("probe_points", 0),
    ],
)
def test_bad_probe_settings_are_refused(field: str, value: float) -> None:
    with pytest.raises(ValueError, match=field):
        ReconstructionConfig(dims=6, **{field: value})


@pytest.mark.parametrize("away, extra", [(True, 1), (False, 2)])
def test_probe_adds_refits_per_member_to_the_step_count(away: bool, extra: int) -> None:
    """One more refit per member where the probe looks on one side, two on both."""
    plain = ReconstructionConfig(dims=6, probe_unseen=0.0)
    probed = ReconstructionConfig(dims=6, probe_unseen=0.05, probe_away=away)
    members = plain.snapshots - plain.burn_in
    assert probed.total_steps - plain.total_steps == extra * members * plain.refit_steps


def _moved(state: dict, t: float) -> dict:
    """``state`` moved by ``t`` along its px-pz direction (as training may
    leave a member before the placement)."""
    mu, cov = member_moments(state, 6, 8, 2, PLACEMENT_PARTICLES, CONFIG.seed)
    v = unseen_directions(_maps(), cov)
    target = cov + t * v[traded_pairs(v, cov).index(PROBE_PAIR)]
    return _fold(state, transport_map(cov, target), mu)


@pytest.mark.parametrize("trained_at", [-0.04, 0.04])
def test_probe_looks_away_from_where_training_left_the_members(
    trained_at: float,
) -> None:
    """``probe_away``: the members' trained ``t`` is recorded, and only the
    side away from it is probed; a better fit on the trained side is refused
    (a refitted member's memory, not evidence), one on the far side taken."""
    members = [_placed_member(0), _placed_member(1)]
    trained = [_moved(m, trained_at) for m in members]
    config = ReconstructionConfig(
        dims=6, width=8, depth=2, probe_unseen=0.05, probe_gain=1e-4
    )

    def run(best_t: float, config=config) -> dict:
        best = _partial_at(members[0], best_t)

        def score(state):
            return (_partial(_cov(state), 1, 5) - best) ** 2

        _, record = probe_members(
            members, lambda k, s, h, c: s, score, config, _maps(), trained=trained
        )
        return record

    away = -1.0 if trained_at > 0 else 1.0
    toward = run(-away * 0.1)  # the images prefer the trained side
    assert toward["trained_t"] == pytest.approx([trained_at] * 2, abs=2e-3)
    assert [s["t"] for s in toward["steps"]] == pytest.approx([0, away * 0.05])
    assert toward["t"] == 0.0
    found = run(away * 0.1)  # they prefer the far side: two steps there
    assert found["t"] == pytest.approx(away * 0.1)
    assert [s["t"] for s in found["steps"]] == pytest.approx(
        [0, away * 0.05, away * 0.1]
    )
    # without probe_away both sides are probed, and the trained side taken
    both = run(-away * 0.1, dataclasses.replace(config, probe_away=False))
    assert both["t"] == pytest.approx(-away * 0.1)


def test_probe_records_the_points_past_the_positive_definite_edge() -> None:
    """A step past a member's edge (this beam: +0.54 along px-pz, none on the
    other side) is not tried, and the record says so; the other side is."""
    members = [_placed_member(0), _placed_member(1)]
    config = dataclasses.replace(CONFIG, probe_unseen=0.6, probe_points=1)
    cov = _cov(members[0])
    v = unseen_directions(_maps(), cov)
    along = v[traded_pairs(v, cov).index(PROBE_PAIR)]
    assert torch.linalg.eigvalsh(cov + 0.6 * along).min() < 0
    assert torch.linalg.eigvalsh(cov - 0.6 * along).min() > 0
    _, record, holds = _probe(members, 0.0, 1.0, config)
    assert record["not_positive_definite"] == [0.6]
    assert [s["t"] for s in record["steps"]] == pytest.approx([0, -0.6])
    assert len(holds) == 2 * 2  # each member at 0 and -0.6 only
    # inside the edge nothing is recorded
    _, record, _ = _probe(members, 0.0, 1.0)
    assert record["not_positive_definite"] == []
