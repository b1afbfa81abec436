"""The fused Triton path of ``Simulator.move`` / ``integrate`` (backend "triton"; the GPU counterpart of the C++
CPU kernel diffdlo/csrc/cable.cpp, wrapper diffdlo/kernel.py).

Forward: ONE kernel launch per move. Each Triton program takes a block of ``BLOCK_ROPES`` ropes and keeps their
whole chain state (positions and velocities, ``[BLOCK_ROPES, N_PAD]`` tensors, N_PAD the node count rounded up to
a power of two) in registers for the whole move: the substep loop (forces, semi-implicit step with implicit
damping, kinematic grasp overwrite along the straight reference path, release, settle check every
``settle_check_every`` substeps after the release, the ``settle_max_substeps`` cap, the divergence test) runs
inside the kernel, and each rope stops at its own substep (it is frozen by masks while the rest of its block
goes on). Neighbour terms (link vectors, turning angles, link forces scattered to nodes) use ``tl.gather`` along
the node axis. The turning angle uses the same branch-free Cephes atan2 as the C++ kernel's lane groups. Per-rope
physics (k_s, k_b, 1 / node mass, damping factor; ``kernel.physics_columns``) are always passed as (B, 4) columns
(the params' numbers repeated when none are given). Same semantics as the C++ kernel: steps, settled and
diverged flags per rope, and ``fixed_steps`` >= 0 for free evolution (``integrate``).

Backward: NOT a Triton adjoint. ``TritonMove.backward`` recomputes the move on the eager torch path
(``Simulator._move_eager`` / ``integrate``'s substep loop, the reference scheme) under autograd and returns its
vector-Jacobian product: exact gradients of the same scheme (the forward outputs agree to rounding), but the
backward runs at eager speed on the device. A Triton adjoint mirroring cable.cpp's (recomputed trajectory + the
analytic energy Hessian-vector product) is the next step.

Not supported here (the simulator then uses the eager torch path, ``Simulator.triton_unsupported`` says why):
frame recording (``record_every`` > 0 with ``return_info``), the PID controller.

Triton's interpreter (``TRITON_INTERPRET=1``) runs the kernel on CPU tensors; that is how the tests check it
against the eager path on a machine without a GPU.
"""
from __future__ import annotations

import os

import torch

try:                                           # optional: pip install diffdlo[gpu]
    import triton
    import triton.language as tl
    _IMPORT_ERROR: str | None = None
except Exception as exc:                       # pragma: no cover - depends on the environment
    triton = None
    tl = None
    _IMPORT_ERROR = f"triton is not importable ({type(exc).__name__}: {exc}); install it with pip install " \
                    f"'diffdlo[gpu]' (or pip install triton)"

BLOCK_ROPES = 16          # ropes per program (a [16, 32] tile for 20 nodes)
NUM_WARPS = 2


def interpreting() -> bool:
    """Whether Triton runs in its CPU interpreter (TRITON_INTERPRET=1)."""
    return os.environ.get("TRITON_INTERPRET", "0") not in ("", "0")


def available() -> bool:
    """True if triton imports (the kernel compiles on first use per dtype and node count)."""
    return triton is not None


def unavailable_reason() -> str | None:
    return _IMPORT_ERROR


def device_reason(device: torch.device) -> str | None:
    """Why the Triton kernel cannot run on ``device`` (None: it can)."""
    if not available():
        return _IMPORT_ERROR
    device = torch.device(device)
    if device.type == "cuda":
        return None
    if device.type == "cpu" and interpreting():
        return None
    if device.type == "cpu":
        return ("the Triton kernel runs on CUDA tensors; on the CPU only in Triton's interpreter (set "
                "TRITON_INTERPRET=1 before Python starts, as the tests do); use backend 'kernel' or 'auto' on the CPU")
    return f"the Triton kernel runs on CUDA tensors, not on {device}"


if triton is not None:
    @triton.jit
    def _atan2(y, x):
        """Branch-free atan2 (Cephes atan rational approximation, as fast_atan2 in cable.cpp)."""
        ax = tl.abs(x)
        ay = tl.abs(y)
        swap = ay > ax
        num = tl.where(swap, ax, ay)
        den = tl.where(swap, ay, ax)
        t = tl.where(den > 0, num / tl.where(den > 0, den, 1.0), 0.0)
        big = t > 0.66
        base = tl.where(big, 0.78539816339744830962, 0.0)
        more = tl.where(big, 0.5 * 6.123233995736765886130E-17, 0.0)
        t = tl.where(big, (t - 1.0) / (t + 1.0), t)
        z = t * t
        p = (((-8.750608600031904122785E-1 * z + -1.615753718733365076637E1) * z
              + -7.500855792314704667340E1) * z + -1.228866684490136173410E2) * z + -6.485021904942025371773E1
        q = ((((z + 2.485846490142306297962E1) * z + 1.650270098316988542046E2) * z
              + 4.328810604912902668951E2) * z + 4.853903996359136964868E2) * z + 1.945506571482613964425E2
        r = base + (t * (z * p / q) + t + more)
        r = tl.where(swap, 1.57079632679489661923 - r + 6.123233995736765886130E-17, r)
        r = tl.where(x < 0, 3.14159265358979323846 - r + 1.2246467991473532e-16, r)
        return tl.where(y < 0, -r, r)

    @triton.jit
    def _move_kernel(pos_ptr, vel_ptr, node_ptr, delta_ptr, speed_ptr, ngrasp_ptr, phys_ptr,
                     out_pos_ptr, out_vel_ptr, steps_ptr, settled_ptr, diverged_ptr,
                     B, l0, h, threshold, radius, check_every, max_settle, fixed_steps,
                     N: tl.constexpr, N_PAD: tl.constexpr, BLOCK: tl.constexpr, FIXED: tl.constexpr):
        pid = tl.program_id(0)
        rope = pid * BLOCK + tl.arange(0, BLOCK)                   # [R]
        rmask = rope < B
        j = tl.arange(0, N_PAD)                                    # [N_PAD]
        jj = j[None, :] + tl.zeros([BLOCK, N_PAD], tl.int32)       # node index, [R, N_PAD]
        nmask = rmask[:, None] & (jj < N)
        link = (jj < N - 1) & rmask[:, None]                       # link j: node j -> j + 1 (real ropes)
        inner = (jj >= 1) & (jj < N - 1)                           # interior nodes (turning angles)
        nxt = tl.minimum(jj + 1, N_PAD - 1)
        prv = tl.maximum(jj - 1, 0)
        rope64 = rope.to(tl.int64)
        offs = rope64[:, None] * (2 * N) + 2 * jj                  # x of node j of rope r; y at +1
        x = tl.load(pos_ptr + offs, mask=nmask, other=0.0)
        y = tl.load(pos_ptr + offs + 1, mask=nmask, other=0.0)
        vx = tl.load(vel_ptr + offs, mask=nmask, other=0.0)
        vy = tl.load(vel_ptr + offs + 1, mask=nmask, other=0.0)
        zero2 = x * 0.0
        ks = tl.load(phys_ptr + rope64 * 4, mask=rmask, other=1.0).to(x.dtype)[:, None]
        kb = tl.load(phys_ptr + rope64 * 4 + 1, mask=rmask, other=0.0).to(x.dtype)[:, None]
        inv_m = tl.load(phys_ptr + rope64 * 4 + 2, mask=rmask, other=1.0).to(x.dtype)[:, None]
        damp = tl.load(phys_ptr + rope64 * 4 + 3, mask=rmask, other=1.0).to(x.dtype)[:, None]
        hm = h * inv_m
        g = tl.load(node_ptr + rope, mask=rmask, other=0).to(tl.int32)          # [R]
        ng = tl.load(ngrasp_ptr + rope, mask=rmask, other=0).to(tl.int32)
        dx = tl.load(delta_ptr + rope64 * 2, mask=rmask, other=0.0)
        dy = tl.load(delta_ptr + rope64 * 2 + 1, mask=rmask, other=0.0)
        sp = tl.load(speed_ptr + rope, mask=rmask, other=1.0)
        safe = tl.maximum(tl.sqrt(dx * dx + dy * dy), 1e-12)
        grasped = jj == g[:, None]
        sx = tl.sum(tl.where(grasped, x, 0.0), axis=1)
        sy = tl.sum(tl.where(grasped, y, 0.0), axis=1)

        active = rmask
        steps = tl.zeros([BLOCK], tl.int32)
        settled = rope < 0
        diverged = rope < 0
        k = 0
        running = tl.max(active.to(tl.int32), axis=0) > 0
        while running:
            k += 1
            # ---- internal forces at the current positions
            ex = tl.where(link, tl.gather(x, nxt, axis=1) - x, 0.0)
            ey = tl.where(link, tl.gather(y, nxt, axis=1) - y, 0.0)
            len2 = tl.where(link, ex * ex + ey * ey, 1.0)
            pex = tl.gather(ex, prv, axis=1)                       # incoming link of node j
            pey = tl.gather(ey, prv, axis=1)
            beta = tl.where(inner, _atan2(pex * ey - pey * ex, pex * ex + pey * ey), 0.0)   # angle at node j
            beta_end = tl.where(link, tl.gather(beta, nxt, axis=1), 0.0)                     # angle at node j + 1
            a = ks * (1.0 - l0 / tl.sqrt(len2))
            b = kb * (beta - beta_end) / len2
            gx = tl.where(link, a * ex - b * ey, 0.0)
            gy = tl.where(link, a * ey + b * ex, 0.0)
            fx = gx - tl.where(jj > 0, tl.gather(gx, prv, axis=1), 0.0)
            fy = gy - tl.where(jj > 0, tl.gather(gy, prv, axis=1), 0.0)
            # ---- semi-implicit Euler with implicit damping
            nvx = (vx + hm * fx) * damp
            nvy = (vy + hm * fy) * damp
            nx = x + h * nvx
            ny = y + h * nvy
            # ---- kinematic grasp along the reference path
            frac = tl.minimum(k * h * sp / safe, 1.0)
            frac_prev = tl.minimum((k - 1) * h * sp / safe, 1.0)
            on_path = grasped & (k <= ng)[:, None]
            rvel = (frac - frac_prev) / h
            nx = tl.where(on_path, (sx + frac * dx)[:, None] + zero2, nx)
            ny = tl.where(on_path, (sy + frac * dy)[:, None] + zero2, ny)
            nvx = tl.where(on_path, (rvel * dx)[:, None] + zero2, nvx)
            nvy = tl.where(on_path, (rvel * dy)[:, None] + zero2, nvy)
            live = active[:, None] & nmask
            x = tl.where(live, nx, x)
            y = tl.where(live, ny, y)
            vx = tl.where(live, nvx, vx)
            vy = tl.where(live, nvy, vy)
            # ---- stop rules
            far = (~(tl.abs(x) <= radius)) | (~(tl.abs(y) <= radius))
            bad = tl.max(tl.where(nmask & far, 1, 0), axis=1) > 0
            if FIXED:
                stop = (k >= fixed_steps) | (rope < 0)
                div_now = stop & bad
                set_now = rope < 0
            else:
                since = k - ng
                check = (since > 0) & ((since % check_every) == 0)
                capped = since >= max_settle
                v2 = tl.max(tl.where(nmask, vx * vx + vy * vy, 0.0), axis=1)
                div_now = (check | capped) & bad
                set_now = check & (~bad) & (tl.sqrt(v2) < threshold)
                stop = div_now | set_now | capped
            newly = active & stop
            steps = tl.where(newly, k, steps)
            settled = settled | (newly & set_now)
            diverged = diverged | (newly & div_now)
            active = active & (~stop)
            running = tl.max(active.to(tl.int32), axis=0) > 0
        tl.store(out_pos_ptr + offs, x, mask=nmask)
        tl.store(out_pos_ptr + offs + 1, y, mask=nmask)
        tl.store(out_vel_ptr + offs, vx, mask=nmask)
        tl.store(out_vel_ptr + offs + 1, vy, mask=nmask)
        tl.store(steps_ptr + rope, steps.to(tl.int64), mask=rmask)
        tl.store(settled_ptr + rope, settled.to(tl.int8), mask=rmask)
        tl.store(diverged_ptr + rope, diverged.to(tl.int8), mask=rmask)


def default_columns(p, batch: int, device, dtype) -> torch.Tensor:
    """(B, 4) k_s, k_b, 1 / node_mass, damping factor of the params, for every rope."""
    row = torch.tensor([p.k_s, p.k_b, 1.0 / p.node_mass, 1.0 / (1.0 + p.dt * p.k_d / p.node_mass)],
                       dtype=torch.float64)
    return row.to(device=device, dtype=dtype).expand(batch, 4).contiguous()


def columns(p, physics, batch: int, device, dtype) -> torch.Tensor:
    """(B, 4) columns of a Physics (or the params' numbers for None), on ``device`` in ``dtype`` (detached)."""
    if physics is None:
        return default_columns(p, batch, device, dtype)
    from .kernel import physics_columns
    return physics_columns(p, physics, batch).detach().to(device=device, dtype=dtype).contiguous()


def forward(p, pos, vel, node, delta, speed, n_grasp, phys, fixed_steps: int = -1,
            divergence_radius: float = 100.0):
    """Run the kernel (no autograd): returns (pos, vel, steps int64, settled bool, diverged bool), all on pos's
    device. ``phys``: the (B, 4) columns (``columns``); ``fixed_steps`` >= 0: free evolution for that many substeps
    (node, delta, speed, n_grasp then unused: pass zeros)."""
    reason = device_reason(pos.device)
    if reason is not None:
        raise RuntimeError(f"backend 'triton' cannot run: {reason}")
    batch, n = pos.shape[0], p.n_nodes
    dev = pos.device
    pos = pos.detach().contiguous()
    vel = vel.detach().to(pos.dtype).contiguous()
    node = node.detach().to(device=dev, dtype=torch.int64).contiguous()
    delta = delta.detach().to(device=dev, dtype=pos.dtype).contiguous()
    speed = speed.detach().to(device=dev, dtype=pos.dtype).contiguous()
    n_grasp = n_grasp.detach().to(device=dev, dtype=torch.int64).contiguous()
    phys = phys.detach().to(device=dev, dtype=pos.dtype).contiguous()
    out_pos, out_vel = torch.empty_like(pos), torch.empty_like(pos)
    steps = torch.zeros(batch, dtype=torch.int64, device=dev)
    settled = torch.zeros(batch, dtype=torch.int8, device=dev)
    diverged = torch.zeros(batch, dtype=torch.int8, device=dev)
    if batch > 0:
        grid = (triton.cdiv(batch, BLOCK_ROPES),)
        _move_kernel[grid](pos, vel, node, delta, speed, n_grasp, phys, out_pos, out_vel, steps, settled, diverged,
                           batch, float(p.rest_length), float(p.dt), float(p.settle_threshold),
                           float(divergence_radius), int(p.settle_check_every), int(p.settle_max_substeps),
                           int(fixed_steps), N=n, N_PAD=triton.next_power_of_2(n), BLOCK=BLOCK_ROPES,
                           FIXED=fixed_steps >= 0, num_warps=NUM_WARPS)
    return out_pos, out_vel, steps, settled.bool(), diverged.bool()


def _physics_tensors(physics, batch: int, device, dtype):
    """The four Physics values as (B,) tensors (keeping their graphs) and a rebuild function, for autograd."""
    from .physics import PHYSICAL
    values = []
    for key in PHYSICAL:
        v = getattr(physics, key)
        if torch.is_tensor(v):
            values.append(torch.broadcast_to(v, (batch,)))
        else:
            values.append(torch.full((batch,), float(v), device=device, dtype=dtype))
    return values


class TritonMove(torch.autograd.Function):
    """Differentiable Triton move / free evolution: (pos, vel, delta, k_s, k_b, k_d, mass) -> (pos, vel, steps,
    settled, diverged). The backward recomputes the same move on the eager torch path under autograd (see the
    module docstring). ``delta`` is the already clipped drag; ``path_steps`` its substep count; ``fixed_steps`` >=
    0 makes it ``integrate``. k_s, ..., mass: (B,) tensors, or None for the params' numbers."""

    @staticmethod
    def forward(ctx, sim, pos, vel, node, delta, path_steps, fixed_steps, k_s, k_b, k_d, mass):
        from .physics import Physics
        p = sim.params
        batch = pos.shape[0]
        physics = None if k_s is None else Physics(k_s.detach(), k_b.detach(), k_d.detach(), mass.detach())
        phys = columns(p, physics, batch, pos.device, pos.dtype)
        if fixed_steps >= 0:
            zeros = torch.zeros(batch, dtype=torch.int64, device=pos.device)
            speed = torch.full((batch,), p.max_speed, dtype=pos.dtype, device=pos.device)
            out = forward(p, pos, vel, zeros, torch.zeros(batch, 2, dtype=pos.dtype, device=pos.device), speed,
                          zeros, phys, fixed_steps)
        else:
            from . import control
            speed = control.drag_speed(delta.detach().norm(dim=-1), p)
            out = forward(p, pos, vel, node, delta, speed, path_steps, phys)
        ctx.sim, ctx.fixed_steps = sim, fixed_steps
        ctx.save_for_backward(pos, vel, node, delta, path_steps, k_s, k_b, k_d, mass)
        ctx.mark_non_differentiable(*out[2:])
        return out

    @staticmethod
    def backward(ctx, grad_pos, grad_vel, _steps, _settled, _diverged):
        from .physics import Physics
        pos, vel, node, delta, path_steps, k_s, k_b, k_d, mass = ctx.saved_tensors
        sim = ctx.sim
        needs = ctx.needs_input_grad
        with torch.enable_grad():
            leaves = [t.detach().requires_grad_(bool(w)) if t is not None else None
                      for t, w in zip((pos, vel, delta, k_s, k_b, k_d, mass), needs[1:3] + needs[4:5] + needs[7:])]
            x0, v0, d0, ks0, kb0, kd0, m0 = leaves
            physics = None if ks0 is None else Physics(ks0, kb0, kd0, m0)
            if ctx.fixed_steps >= 0:
                out_pos, out_vel = x0, v0
                for _ in range(ctx.fixed_steps):
                    out_pos, out_vel = sim.substep(out_pos, out_vel, physics=physics)
            else:
                from . import control
                speed = control.drag_speed(d0.norm(dim=-1), sim.params)
                out_pos, out_vel = sim._move_eager(x0, v0, node, d0, speed, path_steps, physics)[:2]
            outputs, grads = [], []
            for o, go in ((out_pos, grad_pos), (out_vel, grad_vel)):
                if go is not None:
                    outputs.append(o)
                    grads.append(go)
            inputs = [t for t in leaves if t is not None and t.requires_grad]
            got = torch.autograd.grad(outputs, inputs, grads, allow_unused=True) if outputs and inputs else []
        it = iter(got)
        res = [next(it) if t is not None and t.requires_grad else None for t in leaves]
        g_pos, g_vel, g_delta, g_ks, g_kb, g_kd, g_m = res
        return None, g_pos, g_vel, None, g_delta, None, None, g_ks, g_kb, g_kd, g_m
