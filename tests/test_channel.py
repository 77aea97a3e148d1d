"""Physics against hand-computed values (docs/model.md §3, §4, §5)."""

from __future__ import annotations

import math

import pytest
import torch

from uabs_rl.env import channel as ch

T = torch.tensor


def test_los_probability_hand_values():
    # d2D <= 18 m: always LoS
    assert ch.los_probability(T([0.0, 10.0, 18.0])).tolist() == [1.0, 1.0, 1.0]
    # d2D = 50: 18/50 + exp(-50/63)(1 - 18/50) = 0.36 + 0.45219 * 0.64 = 0.64940
    # d2D = 100: 0.18 + exp(-100/63) * 0.82 = 0.18 + 0.20452 * 0.82 = 0.34767
    got = ch.los_probability(T([50.0, 100.0]))
    assert got.tolist() == pytest.approx([0.649402, 0.347671], abs=1e-5)
    # h_UT = 18 m: C' = (5/10)^1.5 = 0.35355; at 100 m the factor is
    # 1 + 0.35355 * 1.25 * 1^3 * exp(-100/150) = 1.22690 -> 0.34767 * 1.22690 = 0.42656
    assert ch.los_probability(T([100.0]), h_ut=18.0).item() == pytest.approx(0.426558, abs=1e-5)


def test_pathloss_below_the_uabs():
    # d2D = 0, h = 100, h_UT = 1.5: d3D = 98.5, log10(98.5) = 1.99344
    # LoS:  28 + 22 * 1.99344 + 20 log10(30) = 28 + 43.8556 + 29.5424 = 101.398
    # NLoS: 13.54 + 39.08 * 1.99344 + 29.5424 = 120.986 (> LoS, so NLoS = 120.986)
    d2d, d3d = T([0.0]), T([98.5])
    assert ch.pathloss_los(d2d, d3d, 100.0, 1.5, 30.0).item() == pytest.approx(101.398, abs=1e-3)
    assert ch.pathloss_nlos(d2d, d3d, 100.0, 1.5, 30.0).item() == pytest.approx(120.986, abs=1e-3)


def test_pathloss_at_40_m():
    # d3D = sqrt(40^2 + 98.5^2) = 106.312, log10 = 2.02658
    # LoS: 28 + 22 * 2.02658 + 29.5424 = 102.127; NLoS: 13.54 + 39.08 * 2.02658 + 29.5424 = 122.281
    d2d, d3d = T([40.0]), T([math.hypot(40.0, 98.5)])
    assert ch.pathloss_los(d2d, d3d, 100.0, 1.5, 30.0).item() == pytest.approx(102.127, abs=1e-3)
    assert ch.pathloss_nlos(d2d, d3d, 100.0, 1.5, 30.0).item() == pytest.approx(122.281, abs=1e-3)


def test_pathloss_beyond_the_breakpoint():
    # h = 10, h_UT = 1.5, 3.5 GHz: d'BP = 4 * 9 * 0.5 * 3.5e9 / c = 210.145 m
    assert ch.breakpoint_distance(10.0, 1.5, 3.5) == pytest.approx(210.145, abs=1e-3)
    # paper's heights, 30 GHz: 4 * 99 * 0.5 * 30e9 / 299792458 = 19813.7 m: PL1 everywhere
    assert ch.breakpoint_distance(100.0, 1.5, 30.0) == pytest.approx(19813.7, abs=0.1)
    # d2D = 500: d3D = 500.072; PL2 = 28 + 40 log10(500.072) + 20 log10(3.5)
    #            - 9 log10(210.145^2 + 8.5^2) = 105.031 (PL1 would be 98.260)
    d2d, d3d = T([500.0]), T([math.hypot(500.0, 8.5)])
    assert ch.pathloss_los(d2d, d3d, 10.0, 1.5, 3.5).item() == pytest.approx(105.031, abs=1e-3)


def test_snr():
    # 14 + 0 + 38.48 - 120.986 - (-106.4) = 37.894 dB
    got = ch.snr_db(T([120.986]), 14.0, 0.0, 38.4792, -106.4).item()
    assert got == pytest.approx(37.893, abs=1e-3)


def test_derived_beam_quantities():
    # Φ_beam = 2π(1 - cos 20°)/9 = 0.042102 sr; in "degrees": 0.042102 * 57.2958 = 2.41230
    assert ch.beam_solid_angle(40.0, 9) == pytest.approx(0.0421025, abs=1e-6)
    # G = 41000 / 2.41230^2 = 7045.8 -> 38.479 dB (Table 1 rounds it to 38 dB)
    assert ch.beam_gain_db(40.0, 9) == pytest.approx(38.479, abs=1e-3)
    # cos θ_b = 1 - Φ/(2π) = 0.993299, θ_b = 6.636°, r_b = 100 tan θ_b = 11.635 m
    assert ch.beam_footprint_radius(100.0, 40.0, 9) == pytest.approx(11.635, abs=1e-3)
    # d_th = 2 * 100 * tan 20° = 72.794 m
    assert ch.safety_distance(100.0, 40.0) == pytest.approx(72.794, abs=1e-3)
    # coverage bound: 3 * 9 * π * 11.6351^2 / (350 * 170) = 11483 / 59500 = 0.1930
    assert ch.coverage_bound(3, 9, 11.6351, 350 * 170) == pytest.approx(0.1930, abs=1e-4)


def test_beam_centres_layout():
    c = ch.beam_centres(10.0, 9)
    assert c[0].tolist() == [-20.0, 20.0]  # row 0 north, col 0 west
    assert c[4].tolist() == [0.0, 0.0]
    assert c[8].tolist() == [20.0, -20.0]


def test_vehicle_lands_in_the_right_beam():
    r = ch.beam_footprint_radius(100.0, 40.0, 9)  # 11.635
    p = 2 * r
    dx = T([0.0, p, -p, 0.0, 0.9 * r, 3.5 * r, 1.0])
    dy = T([0.0, p, -p, r + 0.5, 0.9 * r, 0.0, -p - 1.0])
    inside, idx = ch.assign_beams(dx, dy, r, 9)
    # centre -> 4; NE centre -> 2; SW centre -> 6; just north of the centre beam's rim
    # lies 11.135 m from the north centre -> beam 1; (0.9r, 0.9r) is 1.27 r from every
    # centre -> outside; 3.5 r east is beyond the grid -> outside; (1, -p-1) -> beam 7
    assert inside.tolist() == [True, True, True, True, False, False, True]
    assert idx[inside].tolist() == [4, 2, 6, 1, 7]


def test_non_square_beam_count_is_refused():
    with pytest.raises(ValueError, match="square"):
        ch.beam_centres(10.0, 8)


def test_coverage_fraction():
    r = ch.beam_footprint_radius(100.0, 40.0, 9)
    # one UABS in the middle of a 400 m x 400 m area: 9 disjoint discs, 9 π r_b² / 160000
    one = ch.coverage_fraction(torch.tensor([[200.0, 200.0]]), r, 9, 400.0, 400.0, 1.0)
    assert one.item() == pytest.approx(9 * math.pi * r * r / 160000, rel=0.02)
    # two UABS at the same point cover the same area; far apart, twice as much
    same = ch.coverage_fraction(torch.tensor([[200.0, 200.0], [200.0, 200.0]]), r, 9, 400.0,
                                400.0, 1.0)
    apart = ch.coverage_fraction(torch.tensor([[100.0, 100.0], [300.0, 300.0]]), r, 9, 400.0,
                                 400.0, 1.0)
    assert same.item() == pytest.approx(one.item()) and apart.item() == pytest.approx(
        2 * one.item(), rel=0.01)


def test_los_probability_height_term_stops_at_23_m():
    """TR 38.901 UMa: C'(h_UT) grows up to h_UT = 23 m, where the model ends."""
    d = torch.tensor([50.0, 100.0, 200.0])
    assert torch.equal(ch.los_probability(d, 30.0), ch.los_probability(d, 23.0))
    assert (ch.los_probability(d, 23.0) > ch.los_probability(d, 18.0)).all()
    assert torch.equal(ch.los_probability(d, 13.0), ch.los_probability(d, 1.5))


@pytest.mark.parametrize("width, height, m, n_beams, spacing", [
    (350.0, 170.0, 3, 9, 10.0), (350.0, 170.0, 6, 9, 5.0), (350.0, 170.0, 8, 16, 10.0),
    (254.0, 254.0, 3, 4, 7.0)])
def test_coverage_fraction_equals_the_direct_count(width, height, m, n_beams, spacing):
    """The reach-limited count equals testing every sample point against every beam
    centre, for UABS anywhere (edges and corners included) and on the 20 m lattice."""
    r_b = 11.635100534062271
    g = torch.Generator().manual_seed(m)
    anywhere = torch.rand(60, 4, m, 2, generator=g) * torch.tensor([width, height])
    lattice = (torch.randint(0, 9, (60, 4, m, 2), generator=g) * 20.0 + 5.0)
    for pos in (anywhere, lattice, torch.zeros(1, m, 2)):
        xs = torch.arange(spacing / 2, width, spacing)
        ys = torch.arange(spacing / 2, height, spacing)
        gx, gy = torch.meshgrid(xs, ys, indexing="ij")
        pts = torch.stack([gx.flatten(), gy.flatten()], -1)
        centres = (pos[..., :, None, :] + ch.beam_centres(r_b, n_beams)).flatten(-3, -2)
        d2 = ((pts[:, None, :] - centres[..., None, :, :]) ** 2).sum(-1)
        direct = (d2 <= r_b * r_b).any(-1).float().mean(-1)
        assert torch.equal(ch.coverage_fraction(pos, r_b, n_beams, width, height, spacing),
                           direct)


def test_channel_name_dispatches_through_the_registry(monkeypatch, trace_cache):
    """``channel.name`` picks the model of ``channel.CHANNELS`` that the links use; an
    unknown name is refused at start-up naming the registered ones."""
    from dataclasses import replace

    from tests.test_train import smoke
    from uabs_rl.config import ConfigError
    from uabs_rl.env.links import LinkModel
    from uabs_rl.env.params import EnvParams

    class Walled(ch.UMa):  # UMa behind 200 dB of walls: no link reaches SNR_th
        def pathloss_los(self, d2d, d3d):
            return super().pathloss_los(d2d, d3d) + 200.0

        def pathloss_nlos(self, d2d, d3d):
            return super().pathloss_nlos(d2d, d3d) + 200.0

    monkeypatch.setitem(ch.CHANNELS, "walled", Walled)
    # a vehicle right below UABS 0 (the smoke fleet is 3; the others far from it)
    pos, veh = T([[[100.0, 100.0], [300.0, 20.0], [30.0, 150.0]]]), T([[[100.0], [100.0]]])
    present = torch.ones(1, 1, dtype=torch.bool)
    served = {}
    for name in ("uma", "walled"):
        cfg = smoke(trace_cache, f"channel.name={name}")
        links = LinkModel(EnvParams.from_config(cfg.scenario, cfg.channel), torch.device("cpu"))
        assert type(links.model) is ch.CHANNELS[name]
        inside, _, served[name] = links.links(pos, veh, present, torch.Generator())
        assert inside[0, 0].all() and not inside[0, 1:].any()
    assert served["uma"].all() and not served["walled"].any()
    # every registered model, a user's own among them (uma and walled here)
    with pytest.raises(ConfigError, match=r"channel.name='nope' is not a channel model: use "
                                          r"one of " + ", ".join(sorted(ch.CHANNELS))):
        EnvParams.from_config(cfg.scenario, replace(cfg.channel, name="nope"))


@pytest.mark.parametrize("name", sorted(ch.CHANNELS))  # a model of yours among them
def test_every_registered_channel_model_is_a_channel(name, trace_cache):
    """What links.py relies on, for each model of ``CHANNELS``: a LoS probability in
    [0, 1] that does not grow with distance, finite path losses that do not fall with
    distance, NLoS no lower than LoS; and the links of a smoke env built with it (its
    own ``conf/channel/<name>.yaml`` composes and validates: test_validation)."""
    from tests.test_train import smoke
    from uabs_rl.env.links import LinkModel
    from uabs_rl.env.params import EnvParams

    cfg = smoke(trace_cache, f"channel.name={name}")
    p = EnvParams.from_config(cfg.scenario, cfg.channel)
    links = LinkModel(p, torch.device("cpu"))
    model = links.model
    assert type(model) is ch.CHANNELS[name]
    d2d = torch.linspace(0.0, 2000.0, 401)
    d3d = torch.hypot(d2d, torch.tensor(p.altitude - p.h_ut))
    rho = model.los_probability(d2d)
    los, nlos = model.pathloss_los(d2d, d3d), model.pathloss_nlos(d2d, d3d)
    assert ((rho >= 0) & (rho <= 1)).all() and (rho.diff() <= 1e-6).all()
    assert torch.isfinite(los).all() and torch.isfinite(nlos).all()
    assert (los.diff() >= -1e-4).all() and (nlos.diff() >= -1e-4).all()
    assert (nlos >= los - 1e-4).all()
    # a vehicle right below UABS 0, the others far: only UABS 0's footprint holds it
    pos, veh = T([[[100.0, 100.0], [300.0, 20.0], [30.0, 150.0]]]), T([[[100.0], [100.0]]])
    inside, _, served = links.links(pos, veh, torch.ones(1, 1, dtype=torch.bool),
                                    torch.Generator())
    assert inside[0, 0].all() and not inside[0, 1:].any()
    assert served.dtype == torch.bool and not served[0, 1:].any()
