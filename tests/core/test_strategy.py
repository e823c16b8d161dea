"""Densification strategy bookkeeping on tiny models: statistics, clone/split opacities, pruning,
opacity reset and the optimizer's state kept consistent."""

from __future__ import annotations

import math

import pytest
import torch

from core.model import GaussianModel
from core.render import RenderCamera, render
from core.config import DensifyConfig
from core.strategy import MAX_COPIES, DensifyStrategy, relocation
from native.types import RasterOutput


def logit(p: float) -> float:
    return math.log(p / (1 - p))


def tiny_model(n: int = 3) -> GaussianModel:
    m = GaussianModel.from_points(torch.arange(3 * n, dtype=torch.float32).reshape(n, 3))
    with torch.no_grad():
        m.params["scales"].copy_(torch.log(torch.tensor([[0.005, 0.005, 0.005],
                                                         [0.5, 0.2, 0.1],
                                                         [0.3, 0.3, 0.3]] * (n // 3 + 1))[:n]))
        m.params["opacity_c"].copy_(torch.tensor([logit(0.6), logit(0.5), logit(0.4)] * n)[:n])
        m.params["opacity_g"].copy_(torch.tensor([logit(0.3), logit(0.8), logit(0.2)] * n)[:n])
    return m


def fake_output(n: int, absgrad_c, absgrad_g, radii, contribution) -> RasterOutput:
    z = torch.zeros(1, 1, 1)
    return RasterOutput(color=z, geometry=z, depth=z, alpha_c=z, alpha_g=z,
                        radii=torch.tensor(radii, dtype=torch.int32),
                        means2d=torch.zeros(n, 2), absgrad_c=torch.tensor(absgrad_c),
                        absgrad_g=torch.tensor(absgrad_g),
                        contribution=torch.tensor(contribution))


def test_update_accumulates_ndc_absgrad_per_branch():
    s = DensifyStrategy()
    st = s.initialize_state(3)
    out = fake_output(3, [[1e-4, 0.0], [0.0, 2e-4], [5.0, 5.0]], [[0.0, 0.0], [3e-4, 0.0],
                                                                    [1.0, 1.0]],
                      [2, 7, 0], [0.2, 0.5, 0.9])
    s.update(st, out, width=40, height=20)
    s.update(st, out, width=40, height=20)
    # NDC units: x gradients times W/2 = 20, y times H/2 = 10; unseen Gaussian 2 gets nothing.
    torch.testing.assert_close(st.grad_c, torch.tensor([2 * 2e-3, 2 * 2e-3, 0.0]))
    torch.testing.assert_close(st.grad_g, torch.tensor([0.0, 2 * 6e-3, 0.0]))
    torch.testing.assert_close(st.count, torch.tensor([2.0, 2.0, 0.0]))
    torch.testing.assert_close(st.max_radii, torch.tensor([2.0, 7.0, 0.0]))
    torch.testing.assert_close(st.contribution, torch.tensor([0.2, 0.5, 0.9]))
    with pytest.raises(ValueError, match="out"):
        s.update(s.initialize_state(4), out, 40, 20)


def _stepped_optimizer(m: GaussianModel) -> torch.optim.Optimizer:
    opt = m.make_optimizer()
    loss = sum(p.square().sum() for p in m.params.values())
    loss.backward()
    opt.step()
    opt.zero_grad()
    return opt


def test_clone_and_split_opacities_and_adam_state():
    m = tiny_model()
    before = {k: p.detach().clone() for k, p in m.params.items()}
    opt = _stepped_optimizer(m)
    after_step = {k: p.detach().clone() for k, p in m.params.items()}
    moments = {g["name"]: opt.state[g["params"][0]]["exp_avg"].clone() for g in opt.param_groups}
    s = DensifyStrategy(DensifyConfig(), extent=1.0)
    st = s.initialize_state(3)
    # Gaussian 0 (small) passes the appearance threshold only, 1 (large) the geometry one only.
    st.grad_c[:] = torch.tensor([0.01, 0.0, 0.0])
    st.grad_g[:] = torch.tensor([0.0, 0.01, 0.0])
    st.count[:] = 1.0
    st.contribution[:] = torch.tensor([0.3, 0.6, 0.9])
    rec = s.densify(m, opt, st, generator=torch.Generator().manual_seed(0))
    assert rec == {"cloned": 1, "split": 1, "pruned_big": 0, "n": 5}
    assert len(m) == 5
    # Rows: 0 (clone original), 2 (untouched), 3 (clone copy), 4 and 5 -> 3, 4 (split samples).
    o_c, o_g = m.opacity_c.detach(), m.opacity_g.detach()
    o0c = torch.sigmoid(after_step["opacity_c"][0])
    bulo = 1 - torch.sqrt(1 - o0c)
    assert o_c[0].item() == pytest.approx(bulo.item(), rel=1e-5)
    assert o_c[2].item() == pytest.approx(bulo.item(), rel=1e-5)  # the copy
    assert 1 - (1 - o_c[0]) * (1 - o_c[2]) == pytest.approx(o0c.item(), rel=1e-5)
    assert o_g[0].item() == pytest.approx(torch.sigmoid(after_step["opacity_g"][0]).item())
    assert o_g[2].item() == pytest.approx(0.005, rel=1e-4)
    torch.testing.assert_close(m.params["means"][2], after_step["means"][0])
    # Untouched Gaussian 2 is now row 1.
    for k in m.params:
        torch.testing.assert_close(m.params[k][1], after_step[k][2])
    # Split of Gaussian 1: geometry passed -> both Bulo; appearance: first keeps, second 0.005.
    o1g = torch.sigmoid(after_step["opacity_g"][1])
    torch.testing.assert_close(o_g[3:5], (1 - torch.sqrt(1 - o1g)).expand(2), rtol=1e-5, atol=0)
    assert o_c[3].item() == pytest.approx(torch.sigmoid(after_step["opacity_c"][1]).item())
    assert o_c[4].item() == pytest.approx(0.005, rel=1e-4)
    torch.testing.assert_close(m.scales[3:5], (torch.exp(after_step["scales"][1]) / 1.6).expand(2, 3))
    assert not torch.equal(m.params["means"][3], m.params["means"][4])
    assert (m.params["means"][3:5] - after_step["means"][1]).norm(dim=1).max() < 5 * 0.5
    # Optimizer state: kept rows keep their moments, new rows start at zero.
    for group in opt.param_groups:
        p, name = group["params"][0], group["name"]
        assert p is m.params[name]
        ea = opt.state[p]["exp_avg"]
        assert ea.shape == p.shape
        torch.testing.assert_close(ea[0], moments[name][0])
        torch.testing.assert_close(ea[1], moments[name][2])
        assert torch.all(ea[2:] == 0)
    # Statistics: gradients cleared, contribution inherited from the parents.
    assert torch.all(st.grad_c == 0) and torch.all(st.count == 0)
    torch.testing.assert_close(st.contribution, torch.tensor([0.3, 0.9, 0.3, 0.6, 0.6]))
    assert before["means"].shape[0] == 3
    loss = sum(p.square().sum() for p in m.params.values())
    loss.backward()
    opt.step()  # Adam accepts the edited state


def test_nothing_passes_nothing_changes():
    m = tiny_model()
    opt = _stepped_optimizer(m)
    s = DensifyStrategy()
    st = s.initialize_state(3)
    st.grad_c[:] = 1e-4
    st.count[:] = 1.0
    assert s.densify(m, opt, st) == {"cloned": 0, "split": 0, "pruned_big": 0, "n": 3}


def test_too_large_gaussians_go_once_a_reset_has_happened():
    """Scales 0.005, 0.5, 0.3 against 0.1 x extent 4 = 0.4: the 0.5 one is a floater-sized
    sheet; it stays while the first reset has not happened, then goes at a densification and at
    a reset (with its Adam state)."""
    m = tiny_model(6)
    opt = _stepped_optimizer(m)
    s = DensifyStrategy(DensifyConfig(rho=0.0), extent=4.0)
    st = s.initialize_state(6)
    assert s.densify(m, opt, st)["pruned_big"] == 0 and len(m) == 6
    s.prune_and_reset(m, opt, st)
    assert len(m) == 6 and st.resets == 1  # the reset that counts is the one before
    rec = s.densify(m, opt, st)
    assert rec["pruned_big"] == 2 and len(m) == 4
    assert float(m.scales.detach().max()) < 0.4 and len(st.contribution) == 4
    assert all(opt.state[g["params"][0]]["exp_avg"].shape[0] == 4 for g in opt.param_groups)
    with torch.no_grad():
        m.params["scales"][0] = math.log(2.0)
    s.prune_and_reset(m, opt, st)
    assert len(m) == 3
    off = DensifyStrategy(DensifyConfig(rho=0.0, prune_scale=None), extent=4.0)
    m2 = tiny_model(6)
    st2 = off.initialize_state(6)
    st2.resets = 1
    assert off.densify(m2, None, st2)["pruned_big"] == 0 and len(m2) == 6


def test_max_gaussians_caps_growth():
    m = tiny_model(6)
    s = DensifyStrategy(DensifyConfig(max_gaussians=8))
    st = s.initialize_state(6)
    st.grad_c[:] = torch.tensor([0.01, 0.02, 0.03, 0.04, 0.05, 0.06])
    st.count[:] = 1.0
    s.densify(m, None, st)
    assert len(m) == 8  # room for 2: each densified Gaussian adds one row net
    assert st.history[-1]["cloned"] + st.history[-1]["split"] == 2


def test_prune_and_reset():
    n = 20
    m = tiny_model(n)
    with torch.no_grad():
        m.params["opacity_c"][5] = logit(0.001)
        m.params["opacity_g"][5] = logit(0.002)   # transparent in both: pruned
        m.params["opacity_c"][6] = logit(0.001)   # transparent in one branch only: kept
    opt = _stepped_optimizer(m)
    s = DensifyStrategy()
    st = s.initialize_state(n)
    st.contribution[:] = torch.linspace(0.05, 1.0, n)
    st.contribution[6] = 0.99
    ids = m.params["means"][:, 0].detach().clone()
    rec = s.prune_and_reset(m, opt, st)
    # rho 0.1 of 20 -> the 2 lowest contributions (0, 1), plus 5.
    assert rec["pruned"] == 3 and len(m) == 17
    kept = set(m.params["means"][:, 0].tolist())
    assert kept == set(ids.tolist()) - {ids[0].item(), ids[1].item(), ids[5].item()}
    assert st.rho == pytest.approx(0.075)
    assert m.opacity_c.max() <= 0.01 + 1e-6 and m.opacity_g.max() <= 0.01 + 1e-6
    assert m.opacity_c.min() < 0.002  # min(o, 0.01), not a constant
    assert torch.all(st.contribution == 0)
    for group in opt.param_groups:
        p = group["params"][0]
        assert opt.state[p]["exp_avg"].shape == p.shape
        if group["name"].startswith("opacity"):
            assert torch.all(opt.state[p]["exp_avg"] == 0)
    s.prune_and_reset(m, opt, st)
    assert st.rho == pytest.approx(0.1 * 0.75**2) and st.resets == 2


def test_a_reset_without_the_opacity_reset():
    """`reset_opacity` off (released gsplat 1.5.3): the reset step prunes, counts and decays rho
    as before, opacities and their Adam moments are left as they were, and the too-big pruning
    starts after it as after a real reset."""
    m = tiny_model(6)
    opt = _stepped_optimizer(m)
    s = DensifyStrategy(DensifyConfig(rho=0.0, reset_opacity=False), extent=4.0)
    st = s.initialize_state(6)
    before = {k: m.params[k].detach().clone() for k in ("opacity_c", "opacity_g")}
    moments = {g["name"]: opt.state[g["params"][0]]["exp_avg"].clone()
               for g in opt.param_groups if g["name"].startswith("opacity")}
    assert before["opacity_c"].sigmoid().max() > 0.01  # a real reset would lower these
    assert s.prune_and_reset(m, opt, st)["pruned"] == 0 and st.resets == 1
    for name, values in before.items():
        assert torch.equal(m.params[name].detach(), values)
    for g in opt.param_groups:
        if g["name"] in moments:
            assert torch.equal(opt.state[g["params"][0]]["exp_avg"], moments[g["name"]])
            assert bool(moments[g["name"]].abs().sum() > 0)
    assert s.densify(m, opt, st)["pruned_big"] == 2 and len(m) == 4


def test_tied_opacity_prunes_on_appearance_alone():
    m = tiny_model(3)
    with torch.no_grad():
        m.params["opacity_c"][1] = logit(0.001)
    st = DensifyStrategy(DensifyConfig(rho=0.0)).initialize_state(3)
    DensifyStrategy(DensifyConfig(rho=0.0)).prune_and_reset(m, None, st, tied=True)
    assert len(m) == 2


def test_rendered_gradients_drive_densification():
    g = torch.Generator().manual_seed(0)
    pts = torch.randn(30, 3, generator=g) * 0.3 + torch.tensor([0.0, 0.0, 3.0])
    m = GaussianModel.from_points(pts)
    opt = m.make_optimizer()
    cam = RenderCamera(torch.eye(4), torch.tensor([[30.0, 0, 12], [0, 30.0, 12], [0, 0, 1]]),
                       24, 24)
    s = DensifyStrategy(DensifyConfig(grad_threshold_c=1e-6, grad_threshold_g=1e3))
    st = s.initialize_state(len(m))
    target = torch.rand(24, 24, 3, generator=g)
    r = render(m, cam, sh_degree=0, beta=0.3)
    ((r.rgb - target).abs().mean()).backward()
    opt.step()
    s.update(st, r.raster, 24, 24)
    assert st.grad_c.sum() > 0 and st.grad_g.sum() == 0
    seen = int((r.raster.radii > 0).sum())
    rec = s.densify(m, opt, st, generator=g)
    assert rec["cloned"] + rec["split"] == seen
    assert len(m) == 30 + seen
    r2 = render(m, cam, sh_degree=0, beta=0.3)
    ((r2.rgb - target).abs().mean()).backward()
    opt.step()


def test_the_plain_3dgs_settings():
    """3DGS / gsplat DefaultStrategy: the norm of each view's screen gradient (its pixels'
    opposite pulls cancel within the view), clones and splits keeping the opacity, transparent
    Gaussians pruned at every densification, frozen rows left alone."""
    from dataclasses import replace

    from core.config import TrainConfig, method_defaults

    cfg = method_defaults(TrainConfig(), "3dgs").densify
    assert (cfg.gradient, cfg.grad_threshold_c, cfg.revised_opacity, cfg.prune_at, cfg.rho) == (
        "mean", 0.0002, False, "densify", 0.0)
    s = DensifyStrategy(cfg, extent=1.0)
    st = s.initialize_state(3)
    out = fake_output(3, [[1.0, 1.0]] * 3, [[1.0, 1.0]] * 3, [2, 7, 3], [0.2, 0.5, 0.9])
    out.means2d.grad = torch.tensor([[2e-5, 0.0], [0.0, 3e-5], [0.0, 0.0]])
    s.update(st, out, width=40, height=20)
    out.means2d.grad = torch.tensor([[2e-5, 0.0], [0.0, -3e-5], [0.0, 0.0]])
    s.update(st, out, width=40, height=20)
    # Each view's gradient norm in NDC units (x times 20, y times 10); the absgrads are unused.
    torch.testing.assert_close(st.grad_c, torch.tensor([8e-4, 6e-4, 0.0]))
    torch.testing.assert_close(st.grad_g, torch.zeros(3))
    m = tiny_model()
    with torch.no_grad():  # Gaussian 2 transparent, 0 small (clone), 1 large (split)
        m.params["opacity_c"][2] = logit(0.001)
    before = m.opacity_c.detach().clone()
    record = s.densify(m, None, st, torch.Generator().manual_seed(0), tied=True)
    assert (record["cloned"], record["split"], record["pruned"]) == (1, 1, 1)
    # Gaussian 0 and its clone keep 0.6; both samples of the split keep 0.5.
    keep = [float(before[0])] * 2 + [float(before[1])] * 2
    assert sorted(m.opacity_c.tolist()) == pytest.approx(sorted(keep))
    frozen = s.initialize_state(3)
    frozen.frozen = torch.tensor([True, True, True])
    frozen.grad_c += 1.0
    frozen.count += 1.0
    m2 = tiny_model()
    with torch.no_grad():
        m2.params["opacity_c"][2] = logit(0.001)
    assert s.densify(m2, None, frozen, tied=True)["n"] == 3  # nothing grown, nothing pruned
    assert replace(cfg, prune_at="reset").prune_at == "reset"


def test_relocation_keeps_the_cover_of_the_gaussian_it_shares():
    """3DGS-MCMC's Eq. 9 against its definition: one copy changes nothing; n copies keep the
    opacity at the centre (1 - (1 - o')^n = o) and the integral of the alpha along a line
    through it (numerically, on a fine grid); the quadrature equals the paper's alternating
    binomial sum where that sum is exact (small n and o')."""
    o = torch.tensor([0.3, 0.3, 0.05, 0.9, 0.999, 0.6], dtype=torch.float32)
    n = torch.tensor([1, 2, 5, 3, 51, 80])
    scales = torch.tensor([[0.1, 0.2, 0.3]] * 6)
    shared, new_scales = relocation(o, scales, n)
    assert shared[0] == pytest.approx(0.3) and torch.allclose(new_scales[0], scales[0])
    nn = n.clamp(max=MAX_COPIES).double()
    assert torch.allclose(1 - (1 - shared.double()) ** nn, o.double(), atol=1e-6)
    x = torch.linspace(-40, 40, 200_001, dtype=torch.float64)
    for i in range(6):
        c = float(new_scales[i, 0] / scales[i, 0])  # one factor for the three axes
        assert torch.allclose(new_scales[i] / scales[i], torch.full((3,), c), rtol=1e-5)
        one = torch.trapezoid(o[i].double() * torch.exp(-0.5 * x * x), x)
        many = torch.trapezoid(1 - (1 - shared[i].double() * torch.exp(-0.5 * (x / c) ** 2))
                               ** nn[i], x)
        assert float(many) == pytest.approx(float(one), rel=1e-5), i
    for i in range(3):  # the paper's closed form, exact in float64 here
        k = int(nn[i])
        exact = sum(math.comb(k, j) * (-1) ** (j + 1) * float(shared[i]) ** j / math.sqrt(j)
                    for j in range(1, k + 1))
        assert float(new_scales[i, 0] / scales[i, 0]) == pytest.approx(float(o[i]) / exact,
                                                                       rel=1e-5)
    with pytest.raises(ValueError, match="copies"):
        relocation(o, scales, torch.zeros(6, dtype=torch.long))


def test_relocation_moves_the_transparent_onto_live_gaussians():
    """With `relocate` a densification moves the Gaussians transparent in both branches onto
    live ones (none pruned, the count kept), the drawn ones and their copies share the cover
    (same place, opacity 1 - (1 - o)^(1/n)), both have their Adam moments zeroed, the moved
    rows inherit the drawn one's statistics and frozen rows are left alone."""
    n = 12
    m = tiny_model(n)
    with torch.no_grad():
        for i in (2, 7):
            m.params["opacity_c"][i] = logit(0.001)
            m.params["opacity_g"][i] = logit(0.002)
        m.params["opacity_c"][9] = logit(0.001)  # transparent in one branch only: live
        m.params["opacity_c"][4] = logit(0.001)
        m.params["opacity_g"][4] = logit(0.001)
    opt = _stepped_optimizer(m)
    s = DensifyStrategy(DensifyConfig(relocate=True, rho=0.0, grad_threshold_c=1.0,
                                      grad_threshold_g=1.0), extent=100.0)
    st = s.initialize_state(n)
    st.contribution[:] = torch.arange(n, dtype=torch.float32)
    st.frozen = torch.zeros(n, dtype=torch.bool)
    st.frozen[4] = True  # a tracked frame's static scene: never moved
    before = {k: p.detach().clone() for k, p in m.params.items()}
    moments = {g["name"]: opt.state[g["params"][0]]["exp_avg"].clone() for g in opt.param_groups}
    rec = s.densify(m, opt, st, torch.Generator().manual_seed(0))
    assert rec["relocated"] == 2 and "pruned" not in rec and len(m) == n
    assert torch.equal(m.params["means"][4], before["means"][4])
    moved = [2, 7]
    sources = [int(torch.nonzero((before["means"] == m.params["means"][i]).all(dim=1))[0])
               for i in moved]
    assert all(j not in (2, 4, 7) for j in sources)
    copies = {j: sources.count(j) + 1 for j in sources}
    for i, j in zip(moved, sources):
        for name in ("opacity_c", "opacity_g"):  # at least `transparent`: not moved again
            o = torch.sigmoid(before[name][j])
            want = max(float(1 - (1 - o) ** (1 / copies[j])), 0.005)
            got = torch.sigmoid(m.params[name].detach())
            assert float(got[i]) == pytest.approx(want, rel=1e-5)
            assert float(got[j]) == pytest.approx(want, rel=1e-5)
        assert torch.equal(m.params["scales"][i], m.params["scales"][j])
        assert float(st.contribution[i]) == float(j)  # the drawn one's statistics
    others = [i for i in range(n) if i not in moved + sources]
    for group in opt.param_groups:
        state = opt.state[group["params"][0]]["exp_avg"]
        for i in moved + sources:
            assert torch.all(state[i] == 0)
        assert torch.equal(state[others], moments[group["name"]][others])
    # A reset with `relocate` leaves the transparent to the next densification.
    with torch.no_grad():
        m.params["opacity_c"][0] = logit(0.001)
        m.params["opacity_g"][0] = logit(0.001)
    assert s.prune_and_reset(m, opt, st)["pruned"] == 0 and len(m) == n
