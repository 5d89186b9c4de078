"""Anchored fill Gaussians (models/reconstruction/anchors.py): after every optimiser step they lie within their
ball and scale cap, whatever the gradient; they follow pruning and appending; checkpoints keep them."""

import math

import torch

from models.gaussians import Gaussians
from models.reconstruction import ReconstructConfig, Trainer
from models.reconstruction.anchors import Anchors, facing_surfels
from models.reconstruction.reflection_fill import matte_gaussians
from models.tracer import Tracer, TracerConfig


def _fill(n: int, seed: int, scale: float = 0.05) -> Gaussians:
    """A fill as mirror stereo makes them: isotropic matte Gaussians facing the directions they were seen along."""
    gen = torch.Generator().manual_seed(seed)
    pos = torch.rand((n, 3), generator=gen) * 2 - 1
    colour = torch.rand((n, 3), generator=gen)
    facing = torch.nn.functional.normalize(torch.randn((n, 3), generator=gen), dim=1)
    return matte_gaussians(pos, torch.full((n,), scale), 0.3, colour, facing=facing)


def test_projection_bounds_depth_and_spread_separately_and_only_the_anchored_rows():
    gen = torch.Generator().manual_seed(0)
    n = 50
    means, log_scales = torch.randn((n, 3), generator=gen), torch.randn((n, 3), generator=gen) - 3
    quats = torch.randn((n, 4), generator=gen)
    fill = _fill(10, seed=1)
    facing = torch.nn.functional.normalize(torch.randn((10, 3), generator=gen), dim=1)
    fill = facing_surfels(matte_gaussians(fill.means, torch.full((10,), 0.05), 0.3, fill.diffuse, facing=facing))
    means[20:30], quats[20:30], log_scales[20:30] = fill.means, fill.quats, fill.log_scales
    anchors = Anchors(torch.device("cpu"))
    anchors.append(20, fill, depth=3.0, spread=10.0)
    torch.testing.assert_close(anchors.axis.abs(), facing.abs())  # the thin axis: where they were seen from
    moved, turned, scaled = means.clone(), quats.clone(), log_scales.clone()
    moved += torch.randn((n, 3), generator=gen)  # a step of ~1: far beyond 3 x 0.05 along, 10 x 0.05 across
    moved[25] = means[25] + 0.1 * facing[5]  # inside its bounds: stays
    turned += 0.3 * torch.randn((n, 4), generator=gen)
    scaled += 3.0
    target = moved.clone(), turned.clone(), scaled.clone()
    anchors.project(moved, turned, scaled)
    others = torch.ones(n, dtype=torch.bool)
    others[20:30] = False
    for after, before in zip((moved, turned, scaled), target):
        assert torch.equal(after[others], before[others])
    assert torch.equal(moved[25], target[0][25])
    offset = moved[20:30] - means[20:30]
    along = (offset * facing).sum(1)
    across = (offset - along[:, None] * facing).norm(dim=1)
    assert torch.all(along.abs() <= 0.15 + 1e-6) and torch.all(across <= 0.5 + 1e-6)
    assert (along.abs() > 0.15 - 1e-6).sum() >= 5 and (across > 0.5 - 1e-6).sum() >= 5  # the bounds bind
    assert torch.equal(turned[20:30], fill.quats)  # rotation frozen: the thin axis keeps facing the views
    torch.testing.assert_close(scaled[20:30], fill.log_scales + torch.log(torch.tensor([10.0, 10.0, 3.0])))


def test_anchors_follow_the_gaussians_they_were_given_through_pruning():
    anchors = Anchors(torch.device("cpu"))
    fill = _fill(30, seed=3)
    anchors.append(10, _sub(fill, 10, 20), 2.0, 4.0)
    anchors.append(25, _sub(fill, 25, 30), 2.0, 4.0)
    keep = torch.rand(30, generator=torch.Generator().manual_seed(1)) > 0.4
    anchors.keep(keep)
    kept = fill.means[keep]
    assert torch.equal(kept[anchors.index], anchors.centre)  # each anchor still names its own Gaussian
    assert len(anchors) == int(keep[10:20].sum() + keep[25:30].sum())
    anchors.append(0, _sub(fill, 0, 0), 2.0, 4.0)  # nothing to anchor: fine
    assert len(anchors) == int(keep[10:20].sum() + keep[25:30].sum())


def _sub(g: Gaussians, a: int, b: int) -> Gaussians:
    return Gaussians(**{k: v[a:b] for k, v in g.params().items()})


def test_trained_fill_gaussians_stay_anchored_and_checkpoints_keep_the_anchors():
    from stages.benchmark.room_capture import room_capture

    tracer = Tracer(TracerConfig(num_threads=2))
    capture, init = room_capture(tracer, 2000, 2, 32, 24, seed=3)
    config = ReconstructConfig(iterations=100, warmup=0, rays_per_step=256, far_field="off", prune_every=0,
                               checkpoint_every=100, fill_anchor=2.0, fill_spread=5.0)
    trainer = Trainer(capture, init, config, tracer)
    n = len(trainer.params["means"])
    # the fill sits among the room's Gaussians (what the views see), so it gets gradients
    fill = _fill(300, seed=2, scale=0.02)
    with torch.no_grad():
        fill.means.copy_(init.means[torch.randperm(n, generator=torch.Generator().manual_seed(4))[:300]] + 0.01)
    trainer._add_fill(fill, {}, "a test fill", anchored=True)
    trainer._add_fill(_fill(50, seed=5), {}, "a free fill")  # not anchored
    assert len(trainer.anchors) == 300 and torch.equal(trainer.anchors.index, torch.arange(n, n + 300))
    assert "along that direction within 2x their size" in trainer.decisions[-2]
    start = trainer.params["means"].detach().clone()
    for group in trainer.optimizer.param_groups:  # a large learning rate: unanchored they would fly off
        group["lr"] *= 1000 if group["name"] in ("means", "log_scales", "quats") else 1
    trainer.position_lr = lambda step: 1000 * Trainer.position_lr(trainer, step)
    for _ in range(5):
        trainer.train_step()
    means, log_scales = trainer.params["means"].detach(), trainer.params["log_scales"].detach()
    offset = means[n:n + 300] - start[n:n + 300]
    axis = -fill.normals  # the direction each was seen along
    along = (offset * axis).sum(1)
    across = (offset - along[:, None] * axis).norm(dim=1)
    assert torch.all(along.abs() <= 2.0 * 0.02 * (1 + 1e-4)) and torch.all(across <= 5.0 * 0.02 * (1 + 1e-4))
    assert (along.abs() > 0.99 * 2.0 * 0.02).sum() >= 10  # those the rays reach train, held at their bound
    assert torch.equal(trainer.params["quats"].detach()[n:n + 300], facing_surfels(fill).quats)
    assert torch.all(log_scales[n:n + 300] <= math.log(0.02) + torch.log(torch.tensor([5.0, 5.0, 2.0])) + 1e-5)
    assert (means[:n] - start[:n]).norm(dim=1).max() > 6 * 0.02  # the others are free
    # pruning keeps them aligned; a checkpoint carries them into a resumed run
    keep = torch.ones(len(means), dtype=torch.bool)
    keep[::3] = False
    trainer._replace(keep=keep)
    assert len(trainer.anchors) == int(keep[n:n + 300].sum())
    assert torch.equal(trainer.anchors.centre, start[keep][trainer.anchors.index])  # each its own Gaussian's
    resumed = Trainer(capture, init, config, tracer)
    resumed.load_state_dict(trainer.state_dict())
    for name in Anchors.FIELDS:
        assert torch.equal(getattr(resumed.anchors, name), getattr(trainer.anchors, name)), name


def test_facing_surfels_turn_the_local_z_axis_onto_the_normal_and_keep_isotropic_gaussians_the_same():
    from models.gaussians.activations import quats_to_rotmats

    fill = _fill(200, seed=7)
    with torch.no_grad():
        fill.normals[:2] = torch.tensor([[0.0, 0.0, -1.0], [0.0, 0.0, 0.0]])  # no shortest arc; no normal
    turned = facing_surfels(fill)
    z = quats_to_rotmats(turned.quats)[:, :, 2]
    torch.testing.assert_close(z[2:], fill.normals[2:], atol=1e-5, rtol=0)
    torch.testing.assert_close(z[:2], torch.tensor([[0.0, 0.0, -1.0], [0.0, 0.0, 1.0]]), atol=1e-5, rtol=0)
    torch.testing.assert_close(turned.world_to_local().transpose(1, 2) @ turned.world_to_local(),
                               fill.world_to_local().transpose(1, 2) @ fill.world_to_local(), atol=1e-3, rtol=1e-5)
    assert all(torch.equal(getattr(turned, k), getattr(fill, k)) for k in ("means", "log_scales", "diffuse"))


def test_fill_gaussians_keep_their_matte_material_and_checkpoints_keep_which_they_are():
    """fill_matte: what a mirror fill placed keeps F0 and roughness (no buffer sees them; the reflections'
    colour alone made them shiny in the air); the other Gaussians' material trains; off, the fill's trains too."""
    from stages.benchmark.room_capture import room_capture

    tracer = Tracer(TracerConfig(num_threads=2))
    capture, init = room_capture(tracer, 2000, 2, 32, 24, seed=3)
    changed = {}
    for matte in (True, False):
        config = ReconstructConfig(iterations=20, warmup=0, rays_per_step=256, far_field="off", prune_every=0,
                                   fill_matte=matte)
        trainer = Trainer(capture, init, config, tracer)
        n = len(trainer.params["means"])
        fill = _fill(300, seed=2, scale=0.02)
        with torch.no_grad():  # among the room's Gaussians, where the views' buffers reach them
            fill.means.copy_(init.means[torch.randperm(n, generator=torch.Generator().manual_seed(4))[:300]] + 0.01)
        trainer._add_fill(fill, {}, "a test fill", anchored=True)
        trainer._add_fill(_fill(50, seed=5), {}, "highlights")  # not a mirror fill: trains
        assert trainer.reflected.tolist() == [False] * n + [True] * 300 + [False] * 50
        before = {k: trainer.params[k].detach().clone() for k in ("f0", "roughness", "diffuse")}
        for _ in range(5):
            trainer.train_step()
        changed[matte] = {k: (trainer.params[k].detach() != v).reshape(len(v), -1).any(1) for k, v in before.items()}
        if matte:
            resumed = Trainer(capture, init, config, tracer)
            resumed.load_state_dict(trainer.state_dict())
            assert torch.equal(resumed.reflected, trainer.reflected)
            keep = torch.ones(n + 350, dtype=torch.bool)
            keep[::2] = False
            trainer._replace(keep=keep)
            assert torch.equal(trainer.reflected, torch.tensor([False] * n + [True] * 300 + [False] * 50)[keep])
    on, off = changed[True], changed[False]
    for k in ("f0", "roughness"):
        assert not on[k][n:n + 300].any() and on[k][:n].float().mean() > 0.1, k
        assert off[k][n:n + 300].sum() >= 10, k
        assert on[k][n + 300:].any(), k  # the highlights' too
    assert on["diffuse"][n:n + 300].sum() >= 10  # the fill's colour still trains
