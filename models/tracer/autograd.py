"""torch.autograd.Function front of the tracer (forward launches, backward replay)."""

from __future__ import annotations

import torch


class TraceFunction(torch.autograd.Function):
    """Inputs: the raw Gaussian parameters in PARAM_SHAPES order (means [N,3], quats [N,4],
    log_scales [N,3], opacity_logits [N], diffuse [N,3], normals [N,3], roughness [N],
    f0 [N,3]); their geometry was prepared by Tracer.update(). Gradients come back for all."""

    @staticmethod
    def forward(ctx, tracer, origins, dirs, *params):
        state = tracer._forward(origins, dirs, list(params))
        out = tracer._outputs_to_torch(state["outs"], _Like(params[0]))
        ctx.tracer, ctx.state = tracer, state
        ctx.save_for_backward(*params)
        ints = (out.hit_count, out.blended_count, out.candidates, out.obb_candidates)
        ctx.mark_non_differentiable(out.front_depth, *ints)
        return (out.diffuse, out.depth, out.normal, out.roughness, out.f0, out.transmittance, out.front_depth, *ints)

    @staticmethod
    def backward(ctx, g_diffuse, g_depth, g_normal, g_rough, g_f0, g_trans, *_):  # front_depth, counts: none
        inputs = list(ctx.saved_tensors)
        up = {"diffuse": g_diffuse, "depth": g_depth, "normal": g_normal, "roughness": g_rough, "f0": g_f0,
              "transmittance": g_trans}
        with ctx.tracer.timer.section("tracer_host"):
            grads = ctx.tracer._backward(ctx.state, up, inputs)
        return (None, None, None, *grads)


class _Like:
    """Minimal stand-in exposing device/dtype for _outputs_to_torch."""

    def __init__(self, t: torch.Tensor):
        self.device, self.dtype = t.device, t.dtype
