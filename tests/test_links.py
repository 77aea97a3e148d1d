"""The service shortcut (distance radii per LoS state) against a direct SNR computation
written here from docs/model.md §3, for several beam grids, thresholds and LoS modes."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from uabs_rl.config import ChannelConfig, ScenarioConfig
from uabs_rl.env.channel import assign_beams, beam_footprint_radius
from uabs_rl.env.links import LinkModel, footprint_reach
from uabs_rl.env.params import EnvParams

H, H_UT, FC = 100.0, 1.5, 30.0


def direct_snr_db(d2d: np.ndarray, ch: ChannelConfig, gain_db: float, los: bool) -> np.ndarray:
    """TR 38.901 UMa path loss (LoS or NLoS), SNR = P_tx + G_tx + G_rx − PL − P_n."""
    d3d = np.sqrt(d2d ** 2 + (H - H_UT) ** 2)
    d_bp = 4 * (H - 1) * (H_UT - 1) * FC * 1e9 / 299_792_458.0
    pl1 = 28.0 + 22 * np.log10(d3d) + 20 * np.log10(FC)
    pl2 = 28.0 + 40 * np.log10(d3d) + 20 * np.log10(FC) - 9 * np.log10(d_bp ** 2 + (H - H_UT) ** 2)
    pl_los = np.where(d2d <= d_bp, pl1, pl2)
    pl_nlos = np.maximum(pl_los, 13.54 + 39.08 * np.log10(d3d) + 20 * np.log10(FC)
                         - 0.6 * (H_UT - 1.5))
    pl = pl_los if los else pl_nlos
    return ch.tx_power_dbm + ch.tx_gain_db + gain_db - pl - ch.noise_dbm


def rho_los(d2d: np.ndarray) -> np.ndarray:
    d = np.maximum(d2d, 18.0)
    return np.where(d2d <= 18.0, 1.0, 18 / d + np.exp(-d / 63) * (1 - 18 / d))


def setup(n_beams: int, **channel):
    ch = ChannelConfig(n_beams=n_beams, **channel)
    p = EnvParams.from_config(ScenarioConfig(n_uabs=1), ch)
    links = LinkModel(p, torch.device("cpu"))
    # one UABS at the centre, vehicles on a fine grid over its footprints
    pos = torch.tensor([[[175.0, 85.0]]])
    g = torch.linspace(-50.0, 50.0, 201)
    gx, gy = torch.meshgrid(g, g, indexing="ij")
    veh = torch.stack([gx.flatten() + 175.0, gy.flatten() + 85.0])[None]  # [1, 2, V]
    present = torch.ones(1, veh.shape[-1], dtype=torch.bool)
    off = (veh[0] - pos[0, 0][:, None]).double()
    inside, _ = assign_beams(off[0], off[1], p.r_b, n_beams)
    d2d = off.norm(dim=0).numpy()
    return ch, p, links, pos, veh, present, inside.numpy(), d2d


@pytest.mark.parametrize("n_beams", [4, 9, 16, 25])
@pytest.mark.parametrize("los_mode", ["los", "expected"])
@pytest.mark.parametrize("where", ["default", "inside", "above_max"])
def test_shortcut_equals_direct_snr(n_beams, los_mode, where):
    ch0 = ChannelConfig(n_beams=n_beams)
    gain = EnvParams.from_config(ScenarioConfig(), ch0).gain_db
    r_b = beam_footprint_radius(H, ch0.fov_deg, n_beams)
    th = {"default": -13.7,
          # a cut inside the footprints: the SNR of a LoS link at 80 % of the reach
          "inside": float(direct_snr_db(np.array([0.8 * footprint_reach(r_b, n_beams)]), ch0,
                                        gain, True)[0]),
          "above_max": float(direct_snr_db(np.array([0.0]), ch0, gain, True)[0]) + 1.0}[where]
    ch, p, links, pos, veh, present, inside, d2d = setup(n_beams, los_mode=los_mode,
                                                          snr_threshold_db=th)
    if los_mode == "los":
        snr = direct_snr_db(d2d, ch, gain, True)
    else:  # expected path loss: ρ PL_LoS + (1 − ρ) PL_NLoS
        r = rho_los(d2d)
        pl_exp = r * -direct_snr_db(d2d, ch, 0.0, True) + (1 - r) * -direct_snr_db(
            d2d, ch, 0.0, False)
        snr = -pl_exp + gain
    direct = inside & (snr >= th)
    _, _, served = links.links(pos, veh, present, torch.Generator().manual_seed(0))
    assert np.array_equal(served[0].numpy(), direct)
    if where == "above_max":
        assert not direct.any()
    if where == "inside":
        assert direct.any() and not direct[inside].all()


def test_sampled_los_is_drawn_wherever_it_decides_b16():
    """B = 16: between the NLoS and LoS radii, inside the footprints' reach (45.65 m),
    a link is served at the rate ρ_L, not always."""
    ch0 = ChannelConfig(n_beams=16)
    gain = EnvParams.from_config(ScenarioConfig(), ch0).gain_db
    th = float(direct_snr_db(np.array([40.0]), ch0, gain, False)[0])  # NLoS radius 40 m
    ch, p, links, pos, veh, present, inside, d2d = setup(16, snr_threshold_db=th)
    assert not links.always_served
    band = inside & (d2d > 40.5) & (direct_snr_db(d2d, ch, gain, True) >= th)
    assert band.sum() > 50
    gen = torch.Generator().manual_seed(0)
    rate = np.mean([links.links(pos, veh, present, gen)[2][0].numpy()[band].mean()
                    for _ in range(200)])
    expect = rho_los(d2d[band]).mean()
    assert abs(rate - expect) < 0.02, (rate, expect)


def test_shadow_fading_serves_at_the_gaussian_rate():
    """Shadowing on (LoS links): served with probability P(SNR + N(0, σ²) >= SNR_th)."""
    ch0 = ChannelConfig()
    gain = EnvParams.from_config(ScenarioConfig(), ch0).gain_db
    th = float(direct_snr_db(np.array([20.0]), ch0, gain, True)[0])
    ch, p, links, pos, veh, present, inside, d2d = setup(9, los_mode="los", shadow_fading=True,
                                                          snr_threshold_db=th)
    assert not links.radii  # the shortcut is off: SNR per link
    gen = torch.Generator().manual_seed(0)
    rate = np.mean([links.links(pos, veh, present, gen)[2][0].numpy()
                    for _ in range(300)], axis=0)
    z = (th - direct_snr_db(d2d, ch, gain, True)) / ch.shadow_sigma_los_db
    expect = 0.5 * np.array([math.erfc(v / math.sqrt(2)) for v in z])
    assert np.abs(rate[inside] - expect[inside]).max() < 0.12
    assert abs(rate[inside].mean() - expect[inside].mean()) < 0.01
    assert not rate[~inside].any()  # ideal beams: nothing outside a footprint
