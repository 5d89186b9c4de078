"""Gaussian scene: activations, validation, PLY round trip with 3DGS field names."""

import math

import numpy as np
import pytest
import torch
from plyfile import PlyData

from models.gaussians import (
    SH_C0,
    Gaussians,
    quats_to_rotmats,
    random_gaussians,
    read_ply,
    roughness_to_ggx_alpha,
    world_to_local,
    write_ply,
)


def _scene(n=50, seed=0):
    return random_gaussians(n, torch.Generator().manual_seed(seed))


def test_rotmats_are_orthonormal_and_match_known_quaternion():
    q = torch.randn(20, 4, dtype=torch.float64) * 3  # raw: normalised by the activation
    r = quats_to_rotmats(q)
    eye = torch.eye(3, dtype=torch.float64).expand(20, 3, 3)
    torch.testing.assert_close(r @ r.transpose(1, 2), eye, atol=1e-12, rtol=0)
    assert torch.allclose(torch.linalg.det(r), torch.ones(20, dtype=torch.float64))
    # 90 degrees about z: x -> y
    h = math.sqrt(0.5)
    rz = quats_to_rotmats(torch.tensor([[h, 0.0, 0.0, h]], dtype=torch.float64))[0]
    torch.testing.assert_close(rz @ torch.tensor([1.0, 0, 0], dtype=torch.float64),
                               torch.tensor([0.0, 1, 0], dtype=torch.float64), atol=1e-12, rtol=0)


def test_world_to_local_maps_scaled_axes_to_unit_vectors():
    g = _scene().to(dtype=torch.float64)
    m = world_to_local(g.quats, g.log_scales)                      # [N, 3, 3]
    axes = quats_to_rotmats(g.quats) * torch.exp(g.log_scales)[:, None, :]  # columns R S e_i
    torch.testing.assert_close(m @ axes, torch.eye(3, dtype=torch.float64).expand_as(m), atol=1e-10, rtol=0)
    assert torch.equal(roughness_to_ggx_alpha(torch.tensor([0.5])), torch.tensor([0.25]))


def test_validation_names_the_bad_field():
    g = _scene(5)
    params = g.params()
    params["roughness"] = torch.zeros(5, 1)
    with pytest.raises(ValueError, match="roughness"):
        Gaussians(**params)
    params = g.params()
    params["f0"] = [[0.0] * 3] * 5
    with pytest.raises(TypeError, match="f0"):
        Gaussians(**params)
    params = g.params()
    params["diffuse"] = params["diffuse"].double()
    with pytest.raises(ValueError, match="diffuse"):
        Gaussians(**params)


def test_ply_round_trip(tmp_path):
    g = _scene(64, seed=3)
    path = tmp_path / "sub" / "gaussians.ply"
    write_ply(path, g)
    back = read_ply(path)
    for name, value in g.params().items():
        torch.testing.assert_close(getattr(back, name), value, atol=1e-6, rtol=1e-6, msg=name)
    assert not list(path.parent.glob("*.tmp")), "temp file left behind"


def test_ply_uses_3dgs_field_names(tmp_path):
    g = _scene(8)
    write_ply(tmp_path / "g.ply", g)
    v = PlyData.read(str(tmp_path / "g.ply"))["vertex"]
    names = set(v.data.dtype.names)
    expected = {"x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2", "opacity",
                "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3",
                "roughness", "f0_0", "f0_1", "f0_2"}
    assert expected <= names
    np.testing.assert_allclose(0.5 + SH_C0 * np.asarray(v["f_dc_1"]), g.diffuse[:, 1].numpy(), atol=1e-6)
    np.testing.assert_allclose(np.asarray(v["rot_0"]), g.quats[:, 0].numpy())   # w first
    np.testing.assert_allclose(np.asarray(v["nz"]), g.normals[:, 2].numpy())
    np.testing.assert_allclose(np.asarray(v["opacity"]), g.opacity_logits.numpy())


def test_read_plain_3dgs_ply_uses_defaults_and_missing_file_is_valueerror(tmp_path):
    g = _scene(4)
    write_ply(tmp_path / "g.ply", g)
    v = PlyData.read(str(tmp_path / "g.ply"))["vertex"].data
    keep = [n for n in v.dtype.names if not n.startswith(("f0_", "roughness", "n"))]
    from plyfile import PlyElement
    plain = np.empty(len(v), dtype=[(n, "f4") for n in keep])
    for n in keep:
        plain[n] = v[n]
    PlyData([PlyElement.describe(plain, "vertex")]).write(str(tmp_path / "plain.ply"))
    back = read_ply(tmp_path / "plain.ply")
    assert torch.all(back.f0 == 0.04) and torch.all(back.roughness == 0) and torch.all(back.normals == 0)
    with pytest.raises(ValueError, match="nope.ply"):
        read_ply(tmp_path / "nope.ply")


def test_empty_scene():
    g = Gaussians.empty()
    assert len(g) == 0 and g.world_to_local().shape == (0, 3, 3)


def test_cat_keeps_order_and_subset_picks_rows():
    a, b = _scene(5, seed=1), _scene(7, seed=2)
    both = Gaussians.cat([a, Gaussians.empty(), b])
    assert len(both) == 12
    for k, v in both.params().items():
        assert torch.equal(v[:5], getattr(a, k)) and torch.equal(v[5:], getattr(b, k))
    mask = torch.zeros(12, dtype=torch.bool)
    mask[[0, 6, 11]] = True
    picked = both.subset(mask)
    assert torch.equal(picked.means, both.means[[0, 6, 11]])
    assert torch.equal(both.subset(torch.tensor([11, 0])).f0, both.f0[[11, 0]])
