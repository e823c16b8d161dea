"""GaussianModel: activations, initialisation, optimizer bookkeeping, PLY layout and round trip."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from core.config import LearningRates
from core.model import PARAM_NAMES, SH_C0, GaussianModel, _nn_sq_dist, means_lr
from core.plyio import gaussian_ply_properties


def random_model(n: int = 7, seed: int = 0) -> GaussianModel:
    g = torch.Generator().manual_seed(seed)
    shapes = {"means": (n, 3), "scales": (n, 3), "quats": (n, 4), "sh0": (n, 1, 3),
              "shN": (n, 15, 3), "opacity_c": (n,), "opacity_g": (n,), "normals": (n, 3),
              "visibility": (n, 1)}
    return GaussianModel({k: torch.randn(s, generator=g) for k, s in shapes.items()})


def test_from_points_scales_colours_and_opacity():
    # A 4x4x4 grid with spacing 0.1: the 3 nearest neighbours all lie at 0.1.
    ax = torch.arange(4) * 0.1
    pts = torch.stack(torch.meshgrid(ax, ax, ax, indexing="ij"), dim=-1).reshape(-1, 3)
    colors = torch.rand(pts.shape[0], 3)
    m = GaussianModel.from_points(pts, colors)
    assert len(m) == 64
    torch.testing.assert_close(m.scales, torch.full((64, 3), 0.1), rtol=1e-5, atol=1e-6)
    torch.testing.assert_close(m.opacity_c, torch.full((64,), 0.1))
    torch.testing.assert_close(m.opacity_g, torch.full((64,), 0.1))
    torch.testing.assert_close(m.params["sh0"][:, 0] * SH_C0 + 0.5, colors)
    torch.testing.assert_close(m.quats, torch.tensor([[1.0, 0, 0, 0]]).repeat(64, 1))
    assert m.sh.shape == (64, 16, 3)
    assert torch.all(m.normals.norm(dim=1) > 0.999)


def _chunked_cdist_nn(points: torch.Tensor, k: int = 3, chunk: int = 2048) -> torch.Tensor:
    """The k-nearest mean squared distance as core.model computed it before its k-d tree."""
    out = []
    for start in range(0, points.shape[0], chunk):
        d = torch.cdist(points[start:start + chunk], points).square()
        rows = torch.arange(d.shape[0])
        d[rows, rows + start] = float("inf")
        out.append(d.topk(k, largest=False).values.mean(dim=1))
    return torch.cat(out)


def test_nearest_neighbour_distances_by_kd_tree():
    g = torch.Generator().manual_seed(3)
    pts = torch.randn(5000, 3, generator=g) * 0.3 + torch.tensor([0.2, -0.1, 1.0])
    pts[10] = pts[11]  # coinciding points: each is the other's nearest, at 0
    ours = _nn_sq_dist(pts)
    assert ours.dtype == torch.float32 and ours.shape == (5000,)
    exact = torch.cdist(pts.double()[:200], pts.double(),
                        compute_mode="donot_use_mm_for_euclid_dist")
    exact = exact.square().sort(dim=1).values[:, 1:4].mean(dim=1)  # without itself
    torch.testing.assert_close(ours[:200].double(), exact, rtol=1e-6, atol=0)
    # The old chunked cdist (float32 through a matrix product) within its own rounding.
    torch.testing.assert_close(ours, _chunked_cdist_nn(pts), rtol=2e-3, atol=1e-7)
    assert ours[10] == ours[11] and ours[10] < ours.median()
    assert torch.equal(_nn_sq_dist(pts[:1]), torch.tensor([1e-4]))
    two = (pts[0] - pts[1]).double().square().sum()
    torch.testing.assert_close(_nn_sq_dist(pts[:2]), two.float().expand(2))


def test_bad_inputs_name_the_argument():
    with pytest.raises(ValueError, match="points"):
        GaussianModel.from_points(torch.zeros(5, 2))
    params = dict(random_model(3).params)
    params["quats"] = torch.zeros(3, 3)
    with pytest.raises(ValueError, match="quats"):
        GaussianModel(params)
    with pytest.raises(ValueError, match="mask"):
        random_model(3).keep(torch.ones(4, dtype=torch.bool))


def test_learning_rates_follow_3dgs():
    m = random_model()
    opt = m.make_optimizer(LearningRates(), extent=2.0)
    lr = {g["name"]: g["lr"] for g in opt.param_groups}
    assert set(lr) == set(PARAM_NAMES)
    assert lr["means"] == pytest.approx(3.2e-4)
    assert lr["sh0"] == pytest.approx(2.5e-3) and lr["shN"] == pytest.approx(1.25e-4)
    assert lr["opacity_c"] == lr["opacity_g"] == pytest.approx(5e-2)
    assert lr["scales"] == pytest.approx(5e-3) and lr["quats"] == pytest.approx(1e-3)
    rates = LearningRates()
    assert means_lr(rates, 2.0, 0) == pytest.approx(3.2e-4)
    assert means_lr(rates, 2.0, 30_000) == pytest.approx(3.2e-6)
    assert means_lr(rates, 2.0, 15_000) == pytest.approx(3.2e-5)  # geometric midpoint
    assert means_lr(rates, 2.0, 99_999) == pytest.approx(3.2e-6)


def _step(m: GaussianModel, opt: torch.optim.Optimizer) -> None:
    opt.zero_grad()
    loss = sum((p * (i + 1)).square().sum() for i, p in enumerate(m.params.values()))
    loss.backward()
    opt.step()


def test_extend_and_keep_keep_adam_moments_consistent():
    m = random_model(5)
    opt = m.make_optimizer()
    _step(m, opt)
    before = {g["name"]: opt.state[g["params"][0]]["exp_avg"].clone() for g in opt.param_groups}
    new = {k: torch.ones((2,) + tuple(v.shape[1:])) for k, v in m.params.items()}
    m.extend(new, opt)
    assert len(m) == 7
    for group in opt.param_groups:
        p = group["params"][0]
        assert p is m.params[group["name"]]
        state = opt.state[p]
        assert state["exp_avg"].shape == p.shape and state["exp_avg_sq"].shape == p.shape
        torch.testing.assert_close(state["exp_avg"][:5], before[group["name"]])
        assert torch.all(state["exp_avg"][5:] == 0) and torch.all(state["exp_avg_sq"][5:] == 0)
    _step(m, opt)  # Adam accepts the edited state
    moments = {g["name"]: opt.state[g["params"][0]]["exp_avg_sq"].clone()
               for g in opt.param_groups}
    keep = torch.tensor([True, False, True, True, False, False, True])
    m.keep(keep, opt)
    assert len(m) == 4
    for group in opt.param_groups:
        p = group["params"][0]
        torch.testing.assert_close(opt.state[p]["exp_avg_sq"], moments[group["name"]][keep])
    _step(m, opt)


def test_the_fused_optimizer_updates_as_torchs_default_through_edits():
    # make_optimizer's Adam is fused (one kernel a group): the same steps, extends and keeps
    # give the parameters torch's default Adam gives, to float rounding.
    runs = []
    for fused in (True, None):
        m = random_model(6, seed=3)
        opt = m.make_optimizer(LearningRates(), extent=2.0)
        assert all(g["fused"] for g in opt.param_groups)
        for group in opt.param_groups:
            group["fused"] = fused
        g = torch.Generator().manual_seed(4)
        for i in range(6):
            for p in m.params.values():
                p.grad = torch.randn(p.shape, generator=g)
            opt.step()
            if i == 2:
                m.extend({k: torch.randn((2,) + tuple(v.shape[1:]), generator=g)
                          for k, v in m.params.items()}, opt)
            if i == 4:
                m.keep(torch.tensor([True, False] * 4), opt)
        runs.append(m.params)
    for name in PARAM_NAMES:
        torch.testing.assert_close(runs[0][name], runs[1][name], rtol=1e-5, atol=1e-6)


def test_assign_zeroes_only_that_moment():
    m = random_model(4)
    opt = m.make_optimizer()
    _step(m, opt)
    m.assign("opacity_c", torch.full((4,), -4.0), opt)
    state = {g["name"]: opt.state[g["params"][0]] for g in opt.param_groups}
    assert torch.all(state["opacity_c"]["exp_avg"] == 0)
    assert torch.all(state["means"]["exp_avg"] != 0)
    assert torch.all(m.params["opacity_c"] == -4.0)


@pytest.mark.parametrize("side", [1.0, -1.0])
def test_init_geometry_normals_face_the_cameras(side: float):
    m = random_model(3)
    with torch.no_grad():
        m.params["means"].zero_()
        m.params["quats"].copy_(torch.tensor([[1.0, 0, 0, 0]] * 3))
        m.params["scales"].copy_(torch.log(torch.tensor([[0.01, 0.2, 0.3]] * 3)))
    cams = torch.tensor([[side * 3.0, 1.0, 0.0], [side * 3.0, -1.0, 0.5]])
    m.init_geometry(cams)
    torch.testing.assert_close(m.normals, torch.tensor([[side, 0.0, 0.0]] * 3))
    torch.testing.assert_close(m.params["opacity_g"], m.params["opacity_c"])


def test_init_geometry_faces_the_cameras_that_see_each_gaussian():
    """Two parallel opaque discs facing +-x, a camera on each side: each disc's normal faces the
    camera in front of it. The mean direction to both cameras gets both wrong here (it leans
    towards the farther camera's side by a hair)."""
    from core.render import RenderCamera, seen_directions
    from core.synth.generate import look_at

    m = random_model(2)
    with torch.no_grad():
        m.params["means"].copy_(torch.tensor([[0.2, 0.0, 0.0], [-0.2, 0.0, 0.0]]))
        m.params["quats"].copy_(torch.tensor([[1.0, 0, 0, 0]] * 2))
        m.params["scales"].copy_(torch.log(torch.tensor([[0.005, 0.15, 0.15]] * 2)))
        m.params["opacity_c"].fill_(6.0)  # logit: 0.998, opaque
    K = np.array([[40.0, 0, 32], [0, 40.0, 32], [0, 0, 1]])

    def camera(eye):
        w2c = look_at(np.asarray(eye, float), np.zeros(3), np.array([0.0, 0, 1]))
        return RenderCamera.from_camera(type("C", (), {"world_to_camera": w2c, "K": K,
                                                        "width": 64, "height": 64})())

    cams = [camera([3.0, 0.3, 0.0]), camera([-3.0, 0.3, 0.0])]
    seen = seen_directions(m, cams)
    # Each disc hides the other's centre from the camera on its side.
    assert seen[0, 0] > 0.9 and seen[1, 0] < -0.9
    centers = torch.stack([c.center for c in cams])
    m.init_geometry(centers, seen_from=seen)
    torch.testing.assert_close(m.normals, torch.tensor([[1.0, 0, 0], [-1.0, 0, 0]]))
    m.init_geometry(centers)
    torch.testing.assert_close(m.normals, torch.tensor([[-1.0, 0, 0], [1.0, 0, 0]]))


def test_ply_round_trip_is_bit_identical(tmp_path):
    m = random_model(11, seed=4)
    path = tmp_path / "g.ply"
    m.save_ply(path)
    back = GaussianModel.load_ply(path)
    for name in PARAM_NAMES:
        assert torch.equal(back.params[name], m.params[name]), name


def test_ply_layout_is_standard_3dgs(tmp_path):
    m = random_model(3, seed=1)
    path = tmp_path / "g.ply"
    m.save_ply(path)
    raw = path.read_bytes()
    end = raw.index(b"end_header\n") + len(b"end_header\n")
    lines = raw[:end].decode().splitlines()
    props = [ln.split()[2] for ln in lines if ln.startswith("property")]
    standard = (["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
                + [f"f_rest_{i}" for i in range(45)]
                + ["opacity"] + [f"scale_{i}" for i in range(3)] + [f"rot_{i}" for i in range(4)])
    assert props[:len(standard)] == standard
    assert props[len(standard):] == ["opacity_geo", "normal_x", "normal_y", "normal_z",
                                     "visibility"]
    assert props == gaussian_ply_properties()
    assert all(ln.startswith("property float ") for ln in lines if ln.startswith("property"))
    data = np.frombuffer(raw, dtype="<f4", offset=end).reshape(3, len(props))
    # f_rest is channel-major: f_rest_0..14 are the red coefficients of degrees 1..3.
    np.testing.assert_array_equal(data[:, 9:24], m.params["shN"][:, :, 0].detach().numpy())
    np.testing.assert_array_equal(data[:, props.index("opacity")],
                                  m.params["opacity_c"].detach().numpy())
    np.testing.assert_array_equal(data[:, props.index("scale_1")],
                                  m.params["scales"][:, 1].detach().numpy())


def test_plain_3dgs_ply_loads_with_defaults(tmp_path):
    names = ["x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2"] + [f"f_rest_{i}" for i in range(9)]
    names += ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
    data = np.arange(2 * len(names), dtype="<f4").reshape(2, len(names))
    header = "ply\nformat binary_little_endian 1.0\nelement vertex 2\n"
    header += "".join(f"property float {n}\n" for n in names) + "end_header\n"
    path = tmp_path / "plain.ply"
    path.write_bytes(header.encode() + data.tobytes())
    m = GaussianModel.load_ply(path)
    assert len(m) == 2
    torch.testing.assert_close(m.params["shN"][0, :3, 1], torch.tensor([9.0, 10.0, 11.0]))
    assert torch.all(m.params["shN"][:, 3:] == 0)
    torch.testing.assert_close(m.params["opacity_g"], m.params["opacity_c"])
    assert m.visibility[0, 0].item() == pytest.approx(0.9)
    bad = tmp_path / "bad.ply"
    bad.write_bytes(b"not a ply")
    with pytest.raises(ValueError, match="path"):
        GaussianModel.load_ply(bad)
    assert math.isfinite(float(m.scales.detach().sum()))


def test_replace_rows_checks_its_rows_and_values():
    m = GaussianModel.from_points(torch.zeros(4, 3))
    values = {k: p.detach()[:2].clone() for k, p in m.params.items()}
    with pytest.raises(ValueError, match="distinct"):
        m.replace_rows(torch.tensor([1, 1]), values)
    with pytest.raises(ValueError, match="means"):
        m.replace_rows(torch.tensor([1, 2]), {**values, "means": torch.zeros(3, 3)})
    values["means"] += 5.0
    m.replace_rows(torch.tensor([3, 0]), values)
    assert torch.equal(m.params["means"][3], torch.full((3,), 5.0))
    assert torch.equal(m.params["means"][1], torch.zeros(3))
