"""The fused Triton path of ``Simulator.move`` / ``integrate`` (backend "triton"; the GPU counterpart of the C++
CPU kernel diffdlo/planar/backends/csrc/cable.cpp, wrapper diffdlo/planar/backends/kernel.py).

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

Backward: one launch of ``_adjoint_kernel``, the tile form of cable.cpp's adjoint. When a gradient is wanted the
forward also keeps each rope's state every ``chunk_substeps(K)`` substeps (K the longest possible move, the chunk
the power of two >= sqrt(K): 64 for a 2,001-substep move). The adjoint takes the chunks last first: it recomputes
one chunk from its checkpoint into a per-program scratch buffer, then sweeps back through it with the analytic
Hessian-vector product of the energy, each rope over its own substeps only. Memory is the checkpoints plus one
chunk per block of ropes, about 2 sqrt(K) states per rope instead of K; the work is one recomputed forward plus the
adjoint sweep. It returns the gradients w.r.t. the start positions and velocities, the drag (its reference speed
included) and the per-rope physics columns, which autograd carries on to k_s, k_b, k_d and mass.

The kernels read l0, h and the thresholds from a tensor in the state's dtype: Triton passes Python floats as
float32, and ``tl.where`` of two float literals is float32 too, which would round a float64 move (the forward then
matched the eager path to 2e-11 m; now to rounding, 1e-17).

The release within the drag's last substep (``control.last_substep_fraction``, phi per rope), as the eager path and
the C++ kernel: on substep n_grasp the node goes phi of the way from its free step to the path, and a rope stopped
by the settle cap returns its state phi of the way from substep K - 1 to K (the forward keeps x_K - x_{K-1} in one
more checkpoint slot for the adjoint's d / d phi; the adjoint scales substep K's adjoint by phi and passes 1 - phi
of the output's gradient straight to x_{K-1}).

Frames (``record_every`` > 0) are recorded per rope up to its own stop, as the C++ kernel's, and their gradients go
in at their substeps in the adjoint. Not supported here (the simulator then uses the eager torch path,
``Simulator.why_not["triton"]`` says why): the PID controller.

Triton's interpreter (``TRITON_INTERPRET=1``) runs the kernel on CPU tensors; that is how the tests check it
against the eager path on a machine without a GPU.
"""
from __future__ import annotations

import math
import os

import torch

from .kernel import MoveOutputs, frames_gradient, move_outputs, physics_columns

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
# warps per program: the fewest with which ptxas keeps each kernel in registers on sm_90 with 20 nodes (the variants
# with frames spill 20-60 bytes; `python -m benchmarks.speed.triton_compile` prints them all, no GPU needed)
WARPS = {("move", torch.float32): 2, ("move", torch.float64): 8,
         ("adjoint", torch.float32): 4, ("adjoint", torch.float64): 8}


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
        bigf = tl.where(big, 1.0, 0.0).to(t.dtype)   # where(big, pi/4, 0) of two literals would be float32
        base = bigf * 0.78539816339744830962
        more = bigf * (0.5 * 6.123233995736765886130E-17)
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
    def _links(x, y, link, inner, nxt, prv):
        """Link vectors e_j = x_{j+1} - x_j, their squared lengths (1 off the links) and the turning angle at each
        interior node j (0 elsewhere), for [R, N_PAD] tiles."""
        ex = tl.where(link, tl.gather(x, nxt, axis=1) - x, 0.0)
        ey = tl.where(link, tl.gather(y, nxt, axis=1) - y, 0.0)
        len2 = tl.where(link, ex * ex + ey * ey, 1.0)
        pex = tl.gather(ex, prv, axis=1)                           # incoming link of node j
        pey = tl.gather(ey, prv, axis=1)
        beta = tl.where(inner, _atan2(pex * ey - pey * ex, pex * ex + pey * ey), 0.0)
        return ex, ey, len2, beta

    @triton.jit
    def _substep(x, y, vx, vy, k, live, ks, kb, hm, damp, l0, h, jj, link, inner, nxt, prv,
                 on_path, sx, sy, dx, dy, sp, safe, blend, phi):
        """Substep k of a move for the ropes and nodes in ``live`` (the others keep their state): internal forces,
        semi-implicit Euler with implicit damping, then the grasped node (``on_path``) put on its reference path,
        or, on the ropes in ``blend`` (their last drag substep, phi < 1), the share ``phi`` of the way from its free
        step to the path (control.last_substep_fraction). Mirrors diffdlo/planar/forces.py, integrate.py and
        control.reference (and cable.cpp's substep). Also returns the grasped node's free x, y, vx, vy per rope."""
        ex, ey, len2, beta = _links(x, y, link, inner, nxt, prv)
        beta_end = tl.where(link, tl.gather(beta, nxt, axis=1), 0.0)                     # angle at node j + 1
        a = ks * (1.0 - l0 / tl.sqrt(len2))
        b = kb * (beta - beta_end) / len2
        gx = tl.where(link, a * ex - b * ey, 0.0)
        gy = tl.where(link, a * ey + b * ex, 0.0)
        fx = gx - tl.where(jj > 0, tl.gather(gx, prv, axis=1), 0.0)
        fy = gy - tl.where(jj > 0, tl.gather(gy, prv, axis=1), 0.0)
        nvx = (vx + hm * fx) * damp
        nvy = (vy + hm * fy) * damp
        nx = x + h * nvx
        ny = y + h * nvy
        frac = tl.minimum(k * h * sp / safe, 1.0)
        frac_prev = tl.minimum((k - 1) * h * sp / safe, 1.0)
        rvel = (frac - frac_prev) / h
        zero2 = x * 0.0
        free_x = tl.sum(tl.where(on_path, nx, 0.0), axis=1)
        free_y = tl.sum(tl.where(on_path, ny, 0.0), axis=1)
        free_vx = tl.sum(tl.where(on_path, nvx, 0.0), axis=1)
        free_vy = tl.sum(tl.where(on_path, nvy, 0.0), axis=1)
        share = blend[:, None] & on_path
        w = phi[:, None]
        rx = (sx + frac * dx)[:, None] + zero2
        ry = (sy + frac * dy)[:, None] + zero2
        rvx = (rvel * dx)[:, None] + zero2
        rvy = (rvel * dy)[:, None] + zero2
        nx = tl.where(share, nx + w * (rx - nx), tl.where(on_path, rx, nx))
        ny = tl.where(share, ny + w * (ry - ny), tl.where(on_path, ry, ny))
        nvx = tl.where(share, nvx + w * (rvx - nvx), tl.where(on_path, rvx, nvx))
        nvy = tl.where(share, nvy + w * (rvy - nvy), tl.where(on_path, rvy, nvy))
        return (tl.where(live, nx, x), tl.where(live, ny, y), tl.where(live, nvx, vx), tl.where(live, nvy, vy),
                free_x, free_y, free_vx, free_vy)

    @triton.jit
    def _share(dx, dy, sp, safe, ng, h, vmax):
        """Per rope: phi, the share of the drag's last substep the path still fills (control.last_substep_fraction;
        1 without a drag), and d phi / d (dx, dy) (nonzero only for a slow drag, s = vmax, with 0 < phi < 1)."""
        raw = safe / (sp * h) - (ng - 1).to(safe.dtype)
        inside = (ng > 0) & (raw < 1.0)
        phi = tl.where(inside, tl.minimum(tl.maximum(raw, 0.0), 1.0), 1.0 + safe * 0.0)
        moving = inside & (raw > 0.0) & (~(sp > vmax))
        scale = tl.where(moving, 1.0 / (safe * sp * h), 0.0)
        return phi, dx * scale, dy * scale

    @triton.jit
    def _hvp(x, y, ux, uy, ks, kb, l0, jj, link, inner, nxt, prv):
        """Hessian-vector product H u of the energy at (x, y), and u . F_s, u . F_b (F = k_s F_s + k_b F_b the
        internal forces) per rope: the tile form of cable.cpp's hvp. Link k's gradient dE/de_k = k_s (1 - l0/l) e +
        k_b (beta_start - beta_end) q(e), q(e) = perp(e) / |e|^2; its derivative along we = u_{k+1} - u_k is
        k_s [(1 - l0/l) we + l0/l^3 (e.we) e] + k_b [(dbeta_start - dbeta_end) q + (beta_start - beta_end) dq], with
        dbeta_j = q(e_j).we_j - q(e_{j-1}).we_{j-1} and dq = perp(we)/l^2 - 2 (e.we) perp(e)/l^4."""
        ex, ey, len2, beta = _links(x, y, link, inner, nxt, prv)
        wex = tl.where(link, tl.gather(ux, nxt, axis=1) - ux, 0.0)
        wey = tl.where(link, tl.gather(uy, nxt, axis=1) - uy, 0.0)
        qw = tl.where(link, (ex * wey - ey * wex) / len2, 0.0)                           # q(e_k) . we_k
        dbeta = tl.where(inner, qw - tl.gather(qw, prv, axis=1), 0.0)
        dbend = tl.where(link, beta - tl.gather(beta, nxt, axis=1), 0.0)                  # beta_start - beta_end
        ddbend = tl.where(link, dbeta - tl.gather(dbeta, nxt, axis=1), 0.0)
        ln = tl.sqrt(len2)
        stretch = 1.0 - l0 / ln
        edotw = ex * wex + ey * wey
        c = ks * l0 / (ln * len2)
        l4 = len2 * len2
        qx = -ey / len2
        qy = ex / len2
        dqx = -wey / len2 + 2.0 * edotw * ey / l4
        dqy = wex / len2 - 2.0 * edotw * ex / l4
        gx = tl.where(link, ks * stretch * wex + c * edotw * ex + kb * (ddbend * qx + dbend * dqx), 0.0)
        gy = tl.where(link, ks * stretch * wey + c * edotw * ey + kb * (ddbend * qy + dbend * dqy), 0.0)
        hux = tl.where(jj > 0, tl.gather(gx, prv, axis=1), 0.0) - gx                     # (H u)_j = dG_{j-1} - dG_j
        huy = tl.where(jj > 0, tl.gather(gy, prv, axis=1), 0.0) - gy
        dot_s = -tl.sum(tl.where(link, stretch * edotw, 0.0), axis=1)
        dot_b = -tl.sum(tl.where(link, dbend * qw, 0.0), axis=1)
        return hux, huy, dot_s, dot_b

    @triton.jit
    def _path_adjoint(k, dx, dy, sp, safe, h, vmax, ax, ay, cx, cy):
        """Gradient w.r.t. the drag (dx, dy) of the reference position and velocity at substep k, whose adjoints
        are (ax, ay), (cx, cy) (cable.cpp's reference_adjoint). frac_k = min(1, k h s / |d|): with s = vmax (slow
        drags) d frac / d d = -frac d / |d|^2 while unclamped; a fast drag (s = |d| / (max_drag h)) has a constant
        frac."""
        slow = ~(sp > vmax)
        raw = k * h * sp / safe
        raw_prev = (k - 1) * h * sp / safe
        frac = tl.minimum(raw, 1.0)
        frac_prev = tl.minimum(raw_prev, 1.0)
        dfrac = tl.where(slow & (raw < 1.0), -raw / safe, 0.0)
        dprev = tl.where(slow & (raw_prev < 1.0), -raw_prev / safe, 0.0)
        adot = ax * dx + ay * dy
        cdot = cx * dx + cy * dy
        ux = dx / safe
        uy = dy / safe
        gdx = frac * ax + adot * dfrac * ux + ((frac - frac_prev) * cx + cdot * (dfrac - dprev) * ux) / h
        gdy = frac * ay + adot * dfrac * uy + ((frac - frac_prev) * cy + cdot * (dfrac - dprev) * uy) / h
        return gdx, gdy

    @triton.jit
    def _drag_of(node_ptr, ngrasp_ptr, delta_ptr, speed_ptr, rope, rope64, rmask, jj):
        """Per rope: the grasped node's mask ([R, N_PAD]), the drag's substeps, the drag (dx, dy), its reference
        speed and its length (floored at 1e-12)."""
        g = tl.load(node_ptr + rope, mask=rmask, other=0).to(tl.int32)
        ng = tl.load(ngrasp_ptr + rope, mask=rmask, other=0).to(tl.int32)
        dx = tl.load(delta_ptr + rope64 * 2, mask=rmask, other=0.0)
        dy = tl.load(delta_ptr + rope64 * 2 + 1, mask=rmask, other=0.0)
        sp = tl.load(speed_ptr + rope, mask=rmask, other=1.0)
        safe = tl.maximum(tl.sqrt(dx * dx + dy * dy), 1e-12)
        return jj == g[:, None], ng, dx, dy, sp, safe

    @triton.jit
    def _move_kernel(pos_ptr, vel_ptr, node_ptr, delta_ptr, speed_ptr, ngrasp_ptr, phys_ptr, scalar_ptr,
                     out_pos_ptr, out_vel_ptr, steps_ptr, settled_ptr, diverged_ptr, ckpt_ptr, frames_ptr,
                     B, check_every, max_settle, fixed_steps, slots, every, frame_cap,
                     N: tl.constexpr, N_PAD: tl.constexpr, BLOCK: tl.constexpr, FIXED: tl.constexpr,
                     SAVE: tl.constexpr, CHUNK: tl.constexpr, RECORD: tl.constexpr):
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
        l0 = tl.load(scalar_ptr)
        h = tl.load(scalar_ptr + 1)
        threshold = tl.load(scalar_ptr + 2)
        radius = tl.load(scalar_ptr + 3)
        ks = tl.load(phys_ptr + rope64 * 4, mask=rmask, other=1.0)[:, None]
        kb = tl.load(phys_ptr + rope64 * 4 + 1, mask=rmask, other=0.0)[:, None]
        hm = h * tl.load(phys_ptr + rope64 * 4 + 2, mask=rmask, other=1.0)[:, None]
        damp = tl.load(phys_ptr + rope64 * 4 + 3, mask=rmask, other=1.0)[:, None]
        grasped, ng, dx, dy, sp, safe = _drag_of(node_ptr, ngrasp_ptr, delta_ptr, speed_ptr, rope, rope64, rmask, jj)
        sx = tl.sum(tl.where(grasped, x, 0.0), axis=1)
        sy = tl.sum(tl.where(grasped, y, 0.0), axis=1)
        phi, _, _ = _share(dx, dy, sp, safe, ng, h, tl.load(scalar_ptr + 4))
        ckpt = rope64[:, None] * (slots * 4 * N) + jj              # checkpoint slot 0 of rope r, x of node j
        if SAVE:
            tl.store(ckpt_ptr + ckpt, x, mask=nmask)
            tl.store(ckpt_ptr + ckpt + N, y, mask=nmask)
            tl.store(ckpt_ptr + ckpt + 2 * N, vx, mask=nmask)
            tl.store(ckpt_ptr + ckpt + 3 * N, vy, mask=nmask)
        frame = rope64[:, None] * (frame_cap * 2 * N) + 2 * jj     # frame 0 of rope r, x of node j; y at +1
        if RECORD:
            tl.store(frames_ptr + frame, x, mask=nmask)
            tl.store(frames_ptr + frame + 1, y, mask=nmask)

        active = rmask
        steps = tl.zeros([BLOCK], tl.int32)
        settled = rope < 0
        diverged = rope < 0
        k = 0
        running = tl.max(active.to(tl.int32), axis=0) > 0
        while running:
            k += 1
            live = active[:, None] & nmask
            px = x                                                 # a rope stopped by the settle cap returns its
            py = y                                                 # state phi of the way from these to the next
            pvx = vx
            pvy = vy
            x, y, vx, vy, _, _, _, _ = _substep(x, y, vx, vy, k, live, ks, kb, hm, damp, l0, h, jj, link, inner, nxt,
                                                prv, grasped & (k <= ng)[:, None], sx, sy, dx, dy, sp, safe,
                                                (k == ng) & (phi < 1.0), phi)
            if SAVE:
                if k % CHUNK == 0:                                 # the state after substep k, for the adjoint
                    at = ckpt + (k // CHUNK) * (4 * N)
                    tl.store(ckpt_ptr + at, x, mask=live)
                    tl.store(ckpt_ptr + at + N, y, mask=live)
                    tl.store(ckpt_ptr + at + 2 * N, vx, mask=live)
                    tl.store(ckpt_ptr + at + 3 * N, vy, mask=live)
            # ---- stop rules
            far = (~(tl.abs(x) <= radius)) | (~(tl.abs(y) <= radius))
            bad = tl.max(tl.where(nmask & far, 1, 0), axis=1) > 0
            if FIXED:
                stop = (rope * 0 + k) >= fixed_steps                # a vector: (bool | vector) is int32 interpreted
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
                lerp = (active & capped & (~div_now) & (~set_now) & (phi < 1.0))[:, None] & nmask
                if SAVE:                                           # x_K - x_{K-1}: the adjoint's d x_out / d phi
                    at = ckpt + (slots - 1) * (4 * N)
                    tl.store(ckpt_ptr + at, x - px, mask=lerp)
                    tl.store(ckpt_ptr + at + N, y - py, mask=lerp)
                    tl.store(ckpt_ptr + at + 2 * N, vx - pvx, mask=lerp)
                    tl.store(ckpt_ptr + at + 3 * N, vy - pvy, mask=lerp)
                x = tl.where(lerp, px + phi[:, None] * (x - px), x)
                y = tl.where(lerp, py + phi[:, None] * (y - py), y)
                vx = tl.where(lerp, pvx + phi[:, None] * (vx - pvx), vx)
                vy = tl.where(lerp, pvy + phi[:, None] * (vy - pvy), vy)
            if RECORD:
                if k % every == 0:                                 # frames up to each rope's own stop
                    at = frame + (k // every) * (2 * N)
                    tl.store(frames_ptr + at, x, mask=live)
                    tl.store(frames_ptr + at + 1, y, mask=live)
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

    @triton.jit
    def _adjoint_kernel(pos_ptr, node_ptr, delta_ptr, speed_ptr, ngrasp_ptr, phys_ptr, scalar_ptr, steps_ptr,
                        stopped_ptr, ckpt_ptr, scratch_ptr, gpos_ptr, gvel_ptr, gframes_ptr, out_gpos_ptr, out_gvel_ptr,
                        out_gdelta_ptr, out_gphys_ptr, B, slots, every, frame_cap,
                        N: tl.constexpr, N_PAD: tl.constexpr, BLOCK: tl.constexpr, CHUNK: tl.constexpr,
                        PHYS: tl.constexpr, NC: tl.constexpr, FRAMES: tl.constexpr):
        """The move's vector-Jacobian product, backwards over each rope's own substeps. The trajectory comes back
        chunk by chunk, last chunk first: the forward's checkpoint at the chunk's start, CHUNK substeps recomputed
        into this program's scratch, then the adjoint swept back through them. Per substep (x_k = x_{k-1} + h v_k,
        v_k = damp (v_{k-1} + h/m F(x_{k-1})), F = -grad E): u = g_v + h g_x, g_x -= (h damp / m) H(x_{k-1}) u,
        g_v = damp u; while the node is on its path, the adjoints of its overwritten position and velocity go to the
        drag and the grasp start instead. With PHYS, also the gradients w.r.t. k_s, k_b, 1/m and damp. NC: scratch
        planes per substep (x, y; and vx, vy with PHYS). FRAMES: the incoming gradients of the frames recorded every
        ``every`` substeps are added to g_x at their substeps.

        The release within the last drag substep (control.last_substep_fraction, phi per rope): on substep n_grasp
        the node is free + phi (reference - free), so phi of its adjoint goes to the path and 1 - phi stays on the
        node; a rope stopped by the settle cap (``stopped_ptr`` 0: neither settled nor diverged) returned
        x_{K-1} + phi (x_K - x_{K-1}), so the sweep starts from phi times the output's gradient and adds 1 - phi of
        it after substep K. Both add d phi / d drag times the gradient of phi to the drag's."""
        pid = tl.program_id(0)
        rope = pid * BLOCK + tl.arange(0, BLOCK)
        rmask = rope < B
        j = tl.arange(0, N_PAD)
        jj = j[None, :] + tl.zeros([BLOCK, N_PAD], tl.int32)
        nmask = rmask[:, None] & (jj < N)
        link = (jj < N - 1) & rmask[:, None]
        inner = (jj >= 1) & (jj < N - 1)
        nxt = tl.minimum(jj + 1, N_PAD - 1)
        prv = tl.maximum(jj - 1, 0)
        rope64 = rope.to(tl.int64)
        offs = rope64[:, None] * (2 * N) + 2 * jj
        l0 = tl.load(scalar_ptr)
        h = tl.load(scalar_ptr + 1)
        vmax = tl.load(scalar_ptr + 4)
        ks_r = tl.load(phys_ptr + rope64 * 4, mask=rmask, other=1.0)             # per rope, [R]
        kb_r = tl.load(phys_ptr + rope64 * 4 + 1, mask=rmask, other=0.0)
        hm_r = h * tl.load(phys_ptr + rope64 * 4 + 2, mask=rmask, other=1.0)
        damp_r = tl.load(phys_ptr + rope64 * 4 + 3, mask=rmask, other=1.0)
        ks = ks_r[:, None]
        kb = kb_r[:, None]
        hm = hm_r[:, None]
        damp = damp_r[:, None]
        coef = hm * damp
        grasped, ng, dx, dy, sp, safe = _drag_of(node_ptr, ngrasp_ptr, delta_ptr, speed_ptr, rope, rope64, rmask, jj)
        x0 = tl.load(pos_ptr + offs, mask=nmask, other=0.0)
        y0 = tl.load(pos_ptr + offs + 1, mask=nmask, other=0.0)
        sx = tl.sum(tl.where(grasped, x0, 0.0), axis=1)
        sy = tl.sum(tl.where(grasped, y0, 0.0), axis=1)
        K = tl.load(steps_ptr + rope, mask=rmask, other=0).to(tl.int32)
        phi, _, _ = _share(dx, dy, sp, safe, ng, h, vmax)
        lerped = rmask & (tl.load(stopped_ptr + rope, mask=rmask, other=1) == 0) & (phi < 1.0)
        frame = rope64[:, None] * (frame_cap * 2 * N) + 2 * jj
        gx = tl.load(gpos_ptr + offs, mask=nmask, other=0.0)
        gy = tl.load(gpos_ptr + offs + 1, mask=nmask, other=0.0)
        gvx = tl.load(gvel_ptr + offs, mask=nmask, other=0.0)
        gvy = tl.load(gvel_ptr + offs + 1, mask=nmask, other=0.0)
        ckpt = rope64[:, None] * (slots * 4 * N) + jj
        lerped2 = lerped[:, None] & nmask
        if FRAMES:                                                 # a lerped rope's frame K is its x_out
            last = lerped2 & ((K % every) == 0)[:, None]
            at = frame + (K // every)[:, None].to(tl.int64) * (2 * N)
            gx += tl.load(gframes_ptr + at, mask=last, other=0.0)
            gy += tl.load(gframes_ptr + at + 1, mask=last, other=0.0)
        at = ckpt + (slots - 1) * (4 * N)                          # the forward's x_K - x_{K-1}
        gphi = tl.sum(tl.where(lerped2, gx * tl.load(ckpt_ptr + at, mask=lerped2, other=0.0)
                               + gy * tl.load(ckpt_ptr + at + N, mask=lerped2, other=0.0)
                               + gvx * tl.load(ckpt_ptr + at + 2 * N, mask=lerped2, other=0.0)
                               + gvy * tl.load(ckpt_ptr + at + 3 * N, mask=lerped2, other=0.0), 0.0), axis=1)
        zero = sx * 0.0
        gdx = zero
        gdy = zero
        gsx = zero
        gsy = zero
        acc_s = zero
        acc_b = zero
        acc_w = zero
        plane = tl.arange(0, BLOCK)[:, None] * N_PAD + jj          # this program's [R, N_PAD] tile of one plane
        scratch = scratch_ptr + pid.to(tl.int64) * (CHUNK * NC * BLOCK * N_PAD + 4 * BLOCK)
        free = scratch + CHUNK * NC * BLOCK * N_PAD + tl.arange(0, BLOCK)   # the node's free state on substep ng
        kmax = tl.max(K, axis=0)
        chunks = (kmax + CHUNK - 1) // CHUNK
        for ci in range(0, chunks):
            c = chunks - 1 - ci
            k0 = c * CHUNK
            length = tl.minimum(kmax - k0, CHUNK)
            want = nmask & (K > k0)[:, None]
            at = ckpt + c * (4 * N)
            x = tl.where(want, tl.load(ckpt_ptr + at, mask=want, other=0.0), x0)     # ropes already done:
            y = tl.where(want, tl.load(ckpt_ptr + at + N, mask=want, other=0.0), y0)  # any finite shape
            vx = tl.load(ckpt_ptr + at + 2 * N, mask=want, other=0.0)
            vy = tl.load(ckpt_ptr + at + 3 * N, mask=want, other=0.0)
            for s in range(0, length):                             # recompute: x_{k-1} of substeps k0+1 .. k0+length
                k = k0 + s + 1
                base = scratch + s * (NC * BLOCK * N_PAD)
                tl.store(base + plane, x)
                tl.store(base + BLOCK * N_PAD + plane, y)
                if PHYS:
                    tl.store(base + 2 * BLOCK * N_PAD + plane, vx)
                    tl.store(base + 3 * BLOCK * N_PAD + plane, vy)
                live = want & (k <= K)[:, None]
                x, y, vx, vy, nfx, nfy, nfvx, nfvy = _substep(
                    x, y, vx, vy, k, live, ks, kb, hm, damp, l0, h, jj, link, inner, nxt, prv,
                    grasped & (k <= ng)[:, None], sx, sy, dx, dy, sp, safe, (k == ng) & (phi < 1.0), phi)
                at_release = rmask & (k == ng) & (phi < 1.0)
                tl.store(free, nfx, mask=at_release)
                tl.store(free + BLOCK, nfy, mask=at_release)
                tl.store(free + 2 * BLOCK, nfvx, mask=at_release)
                tl.store(free + 3 * BLOCK, nfvy, mask=at_release)
            tl.debug_barrier()
            for si in range(0, length):                            # the adjoint, back through the chunk
                s = length - 1 - si
                k = k0 + s + 1
                act = rmask & (k <= K)
                if FRAMES:
                    if k % every == 0:                             # (a lerped rope's frame K: in its start)
                        at = frame + (k // every) * (2 * N)
                        seen = (act & ~(lerped & (k == K)))[:, None] & nmask
                        gx += tl.load(gframes_ptr + at, mask=seen, other=0.0)
                        gy += tl.load(gframes_ptr + at + 1, mask=seen, other=0.0)
                drag = act & (k <= ng)
                on = grasped & drag[:, None]
                ax = tl.sum(tl.where(on, gx, 0.0), axis=1)
                ay = tl.sum(tl.where(on, gy, 0.0), axis=1)
                cx = tl.sum(tl.where(on, gvx, 0.0), axis=1)
                cy = tl.sum(tl.where(on, gvy, 0.0), axis=1)
                lastk = lerped & (k == K)                          # x_out = x_{K-1} + phi (x_K - x_{K-1})
                sc = tl.where(lastk, phi, 1.0)                     # (phi through substep K, 1 - phi around it)
                blend = drag & (k == ng) & (phi < 1.0)             # node = free + phi (reference - free)
                if tl.max(blend.to(tl.int32), axis=0) > 0:
                    frac = tl.minimum(k * h * sp / safe, 1.0)
                    step = (frac - tl.minimum((k - 1) * h * sp / safe, 1.0)) / h
                    fx = tl.load(free, mask=blend, other=0.0)
                    fy = tl.load(free + BLOCK, mask=blend, other=0.0)
                    fvx = tl.load(free + 2 * BLOCK, mask=blend, other=0.0)
                    fvy = tl.load(free + 3 * BLOCK, mask=blend, other=0.0)
                    gphi += tl.where(blend, sc * (ax * (sx + frac * dx - fx) + ay * (sy + frac * dy - fy)
                                                  + cx * (step * dx - fvx) + cy * (step * dy - fvy)), 0.0)
                w = tl.where(blend, phi, 1.0)                      # the path's share of the node's adjoint
                pw = sc * w
                pdx, pdy = _path_adjoint(k, dx, dy, sp, safe, h, vmax, pw * ax, pw * ay, pw * cx, pw * cy)
                gdx += tl.where(drag, pdx, 0.0)
                gdy += tl.where(drag, pdy, 0.0)
                gsx += pw * ax
                gsy += pw * ay
                keep = (1.0 - w)[:, None]
                gx = tl.where(on, keep * gx, gx)
                gy = tl.where(on, keep * gy, gy)
                gvx = tl.where(on, keep * gvx, gvx)
                gvy = tl.where(on, keep * gvy, gvy)
                live = act[:, None] & nmask
                ux = gvx + h * gx
                uy = gvy + h * gy
                if tl.max(lastk.to(tl.int32), axis=0) > 0:
                    rest = 1.0 - sc
                    ux = sc[:, None] * ux
                    uy = sc[:, None] * uy
                    gvx = tl.where(live, damp * ux + rest[:, None] * gvx + tl.where(on, (rest * w * cx)[:, None], 0.0),
                                   gvx)
                    gvy = tl.where(live, damp * uy + rest[:, None] * gvy + tl.where(on, (rest * w * cy)[:, None], 0.0),
                                   gvy)
                    gx += tl.where(on, (rest * w * ax)[:, None], 0.0)
                    gy += tl.where(on, (rest * w * ay)[:, None], 0.0)
                else:
                    gvx = tl.where(live, damp * ux, gvx)
                    gvy = tl.where(live, damp * uy, gvy)
                base = scratch + s * (NC * BLOCK * N_PAD)
                px = tl.load(base + plane)
                py = tl.load(base + BLOCK * N_PAD + plane)
                hux, huy, dot_s, dot_b = _hvp(px, py, ux, uy, ks, kb, l0, jj, link, inner, nxt, prv)
                if PHYS:
                    pvx = tl.load(base + 2 * BLOCK * N_PAD + plane)
                    pvy = tl.load(base + 3 * BLOCK * N_PAD + plane)
                    uv = tl.sum(tl.where(nmask, ux * pvx + uy * pvy, 0.0), axis=1)
                    acc_s += tl.where(act, dot_s, 0.0)
                    acc_b += tl.where(act, dot_b, 0.0)
                    acc_w += tl.where(act, uv + hm_r * (ks_r * dot_s + kb_r * dot_b), 0.0)
                gx = tl.where(live, gx - coef * hux, gx)
                gy = tl.where(live, gy - coef * huy, gy)
            tl.debug_barrier()
        if FRAMES:                                                 # frame 0, the start positions
            gx += tl.load(gframes_ptr + frame, mask=nmask, other=0.0)
            gy += tl.load(gframes_ptr + frame + 1, mask=nmask, other=0.0)
        start = grasped & (ng > 0)[:, None]
        gx = tl.where(start, gx + gsx[:, None], gx)
        gy = tl.where(start, gy + gsy[:, None], gy)
        tl.store(out_gpos_ptr + offs, gx, mask=nmask)
        tl.store(out_gpos_ptr + offs + 1, gy, mask=nmask)
        tl.store(out_gvel_ptr + offs, gvx, mask=nmask)
        tl.store(out_gvel_ptr + offs + 1, gvy, mask=nmask)
        _, dphix, dphiy = _share(dx, dy, sp, safe, ng, h, vmax)
        tl.store(out_gdelta_ptr + rope64 * 2, gdx + gphi * dphix, mask=rmask)
        tl.store(out_gdelta_ptr + rope64 * 2 + 1, gdy + gphi * dphiy, mask=rmask)
        if PHYS:
            coef_r = hm_r * damp_r
            tl.store(out_gphys_ptr + rope64 * 4, coef_r * acc_s, mask=rmask)
            tl.store(out_gphys_ptr + rope64 * 4 + 1, coef_r * acc_b, mask=rmask)
            tl.store(out_gphys_ptr + rope64 * 4 + 2, h * damp_r * (ks_r * acc_s + kb_r * acc_b), mask=rmask)
            tl.store(out_gphys_ptr + rope64 * 4 + 3, acc_w, mask=rmask)


def chunk_substeps(longest: int) -> int:
    """Substeps per recomputed chunk of the adjoint: the power of two >= sqrt(longest), at least 8, so each rope
    keeps about 2 sqrt(K) states (checkpoints + one chunk) instead of K."""
    root = math.isqrt(max(longest - 1, 0)) + 1                 # ceil(sqrt(longest)) for longest >= 1
    return max(8, 1 << (root - 1).bit_length())


def scalars(p, device, dtype, divergence_radius: float = 100.0) -> torch.Tensor:
    """[l0, h, settle threshold, divergence radius, max_speed] in the state's dtype. The kernels read them from a
    tensor: Triton passes Python floats as float32, which would round h and l0 of a float64 move."""
    return torch.tensor([p.rest_length, p.dt, p.settle_threshold, divergence_radius, p.max_speed],
                        dtype=dtype, device=device)


def columns(p, physics, batch: int, device, dtype) -> torch.Tensor:
    """(B, 4) k_s, k_b, 1 / node_mass, damping factor 1 / (1 + h k_d / node_mass) of a Physics, on ``device`` in
    ``dtype`` and differentiable where its tensors are; the params' numbers for every rope when ``physics`` is
    None."""
    if physics is None:
        row = torch.tensor([p.k_s, p.k_b, 1.0 / p.node_mass, 1.0 / (1.0 + p.dt * p.k_d / p.node_mass)],
                           dtype=torch.float64)
        return row.to(device=device, dtype=dtype).expand(batch, 4).contiguous()
    return physics_columns(p, physics, batch, device=device, dtype=dtype)


def _longest(p, fixed_steps: int) -> int:
    return fixed_steps if fixed_steps >= 0 else p.max_drag_steps + p.settle_max_substeps + 1


def frame_slots(p, fixed_steps: int, record_every: int) -> int:
    """Frames per rope of a move recording every ``record_every`` substeps: enough for the longest possible move."""
    return _longest(p, fixed_steps) // record_every + 1


def forward(p, pos, vel, node, delta, speed, n_grasp, phys, fixed_steps: int = -1,
            divergence_radius: float = 100.0, save: bool = False, record_every: int = 0):
    """Run the move kernel (no autograd): returns (pos, vel, steps int64, settled bool, diverged bool, checkpoints,
    frames), all on pos's device. ``phys``: the (B, 4) columns (``columns``); ``fixed_steps`` >= 0: free evolution
    for that many substeps (node, delta, speed, n_grasp then unused: pass zeros). ``save``: also keep each rope's
    state every ``chunk_substeps`` substeps for ``backward`` (checkpoints (B, slots, 4, N); None otherwise).
    ``record_every`` > 0: frames (B, frame_slots, N, 2), the positions at substeps 0, E, 2E, ... of each rope up to
    its own stop (rope b's frame j valid for j <= steps[b] // E, as the C++ kernel's; None otherwise)."""
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
    chunk = chunk_substeps(_longest(p, fixed_steps))
    slots = _longest(p, fixed_steps) // chunk + 2          # the last: x_K - x_{K-1} of a rope the cap stopped
    ckpt = pos.new_empty(batch, slots, 4, n) if save else None
    cap = frame_slots(p, fixed_steps, record_every) if record_every > 0 else 0
    frames = pos.new_empty(batch, cap, n, 2) if record_every > 0 else None
    if batch > 0:
        grid = (triton.cdiv(batch, BLOCK_ROPES),)
        _move_kernel[grid](pos, vel, node, delta, speed, n_grasp, phys, scalars(p, dev, pos.dtype, divergence_radius),
                           out_pos, out_vel, steps, settled, diverged, out_pos if ckpt is None else ckpt,
                           out_pos if frames is None else frames,
                           batch, int(p.settle_check_every), int(p.settle_max_substeps), int(fixed_steps), slots,
                           max(int(record_every), 1), cap,
                           N=n, N_PAD=triton.next_power_of_2(n), BLOCK=BLOCK_ROPES, FIXED=fixed_steps >= 0,
                           SAVE=save, CHUNK=chunk, RECORD=record_every > 0, num_warps=WARPS["move", pos.dtype])
    return out_pos, out_vel, steps, settled.bool(), diverged.bool(), ckpt, frames


def backward(p, pos, node, delta, speed, n_grasp, phys, steps, ckpt, grad_pos, grad_vel, fixed_steps: int = -1,
             want_phys: bool = False, grad_frames=None, record_every: int = 0, settled=None, diverged=None):
    """The adjoint of ``forward`` (run with ``save``): returns (grad_pos, grad_vel, grad_delta, grad_phys) for the
    incoming gradients of the final positions and velocities (and of the frames, ``grad_frames`` (B, frame_slots,
    N, 2) of a move recorded every ``record_every`` substeps); grad_phys (B, 4) w.r.t. the columns if
    ``want_phys``, else None. ``settled``, ``diverged``: the forward's flags (a rope with neither was stopped by
    the settle cap, whose release share the adjoint follows). Memory: the checkpoints and one chunk of states per
    block of ropes."""
    batch, n = pos.shape[0], p.n_nodes
    dev, dtype = pos.device, pos.dtype
    n_pad = triton.next_power_of_2(n)
    chunk = chunk_substeps(_longest(p, fixed_steps))
    programs = triton.cdiv(batch, BLOCK_ROPES)
    planes = 4 if want_phys else 2
    scratch = pos.new_empty(max(programs, 1) * (chunk * planes * BLOCK_ROPES * n_pad + 4 * BLOCK_ROPES))
    grad_pos = torch.zeros_like(pos) if grad_pos is None else grad_pos.detach().to(dtype).contiguous()
    grad_vel = torch.zeros_like(pos) if grad_vel is None else grad_vel.detach().to(dtype).contiguous()
    if grad_frames is not None:
        if record_every <= 0:
            raise ValueError("frame gradients need the record_every of the forward that recorded them")
        grad_frames = grad_frames.detach().to(dtype).contiguous()
    out_gpos, out_gvel = torch.empty_like(pos), torch.empty_like(pos)
    out_gdelta = pos.new_empty(batch, 2)
    stopped = torch.ones(batch, dtype=torch.int8, device=dev)       # free evolution: no drag, no release share
    if fixed_steps < 0:
        if settled is None or diverged is None:
            raise ValueError("the adjoint of a move needs the forward's settled and diverged flags")
        stopped = (settled | diverged).to(device=dev, dtype=torch.int8).contiguous()
    out_gphys = pos.new_empty(batch, 4) if want_phys else out_gdelta
    if batch > 0:
        _adjoint_kernel[(programs,)](
            pos.detach().contiguous(), node.to(device=dev, dtype=torch.int64).contiguous(),
            delta.detach().to(dtype).contiguous(), speed.detach().to(dtype).contiguous(),
            n_grasp.to(device=dev, dtype=torch.int64).contiguous(), phys.detach().to(dtype).contiguous(),
            scalars(p, dev, dtype), steps, stopped, ckpt, scratch, grad_pos, grad_vel,
            grad_pos if grad_frames is None else grad_frames, out_gpos, out_gvel, out_gdelta, out_gphys, batch,
            ckpt.shape[1], max(int(record_every), 1), 0 if grad_frames is None else grad_frames.shape[1],
            N=n, N_PAD=n_pad, BLOCK=BLOCK_ROPES, CHUNK=chunk, PHYS=want_phys, NC=planes,
            FRAMES=grad_frames is not None, num_warps=WARPS["adjoint", dtype])
    return out_gpos, out_gvel, out_gdelta, out_gphys if want_phys else None


class TritonMove(torch.autograd.Function):
    """Differentiable Triton move / free evolution: (pos, vel, delta, phys) -> ``kernel.MoveOutputs``, forward and
    backward each one kernel launch. ``delta`` is the already clipped drag (its reference speed is differentiated
    inside the adjoint); ``path_steps`` its substep count; ``fixed_steps`` >= 0 makes it ``integrate``. ``phys``:
    the (B, 4) ``columns``, whose gradient autograd carries on to k_s, k_b, k_d and mass. ``record_every`` > 0:
    frames as ``forward`` returns them (differentiable)."""

    @staticmethod
    def forward(ctx, sim, pos, vel, node, delta, path_steps, fixed_steps, phys, record_every=0) -> MoveOutputs:
        from .. import control
        p = sim.params
        batch = pos.shape[0]
        if fixed_steps >= 0:
            node = path_steps = torch.zeros(batch, dtype=torch.int64, device=pos.device)
            delta = torch.zeros(batch, 2, dtype=pos.dtype, device=pos.device)
            speed = torch.full((batch,), p.max_speed, dtype=pos.dtype, device=pos.device)
        else:
            speed = control.drag_speed(delta.detach().norm(dim=-1), p)
        needs = ctx.needs_input_grad
        save = needs[1] or needs[2] or needs[4] or needs[7]
        out_pos, out_vel, steps, settled, diverged, ckpt, frames = forward(
            p, pos, vel, node, delta, speed, path_steps, phys, fixed_steps, save=save, record_every=record_every)
        ctx.params, ctx.fixed_steps, ctx.record_every = p, fixed_steps, record_every
        ctx.save_for_backward(pos, node, delta, speed, path_steps, phys, steps, ckpt, settled, diverged)
        return move_outputs(ctx, out_pos, out_vel, steps, settled, diverged, frames)

    @staticmethod
    def backward(ctx, grad_pos, grad_vel, _steps, _settled, _diverged, grad_frames):
        pos, node, delta, speed, path_steps, phys, steps, ckpt, settled, diverged = ctx.saved_tensors
        needs = ctx.needs_input_grad
        grad_frames = frames_gradient(grad_frames)
        if grad_pos is None and grad_vel is None and grad_frames is None:
            return (None,) * 9
        g_pos, g_vel, g_delta, g_phys = backward(ctx.params, pos, node, delta, speed, path_steps, phys, steps, ckpt,
                                                 grad_pos, grad_vel, ctx.fixed_steps, want_phys=needs[7],
                                                 grad_frames=grad_frames, record_every=ctx.record_every,
                                                 settled=settled, diverged=diverged)
        return (None, g_pos if needs[1] else None, g_vel if needs[2] else None, None,
                g_delta if needs[4] and ctx.fixed_steps < 0 else None, None, None, g_phys, None)
