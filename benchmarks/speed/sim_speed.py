"""Simulator speed and memory: the default (fused C++ kernel) path against the eager PyTorch reference loop.

    python benchmarks/speed/sim_speed.py [--batches 1 64 1024] [--device cpu] [--repeats 3]

The eager reference is ``Simulator(backend="torch")``: the plain per-substep PyTorch loop of the same scheme at
dt = 1 ms, run in the same process on the same inputs. For each batch size B it prints
- env steps/s: ropes moved per second by one batched ``move()`` (drag + settle), and the ratio to eager;
- sim s/s: simulated seconds per wall second of free evolution (1 s, 1000 substeps), and the ratio to eager;
- deviation: max node distance [mm] of the float32 default path from the float64 eager reference after one
  move and after 1 s of free evolution (first 64 ropes);
- bwd/fwd: time of backward of one move over its forward (default path);
then the peak memory of the gradient of a 10-move sequence at B=256 (measured in a fresh subprocess), and a final
JSON line with every figure. Timings are medians of --repeats runs; the machine's other load shows up in them.

    python benchmarks/speed/sim_speed.py --device cuda [--batches 1 64 1024 16384 65536] [--eager-max 1024]

On CUDA it compares, for each B, the fused Triton kernel (backend "triton", one launch per move), the eager torch
path on the same GPU (up to B = --eager-max: it is slow) and the CPU C++ kernel in the same run (up to
--cpu-max): env steps/s of one batched move, sim s/s of 1 s of free evolution, forward+backward time of one move
(the Triton adjoint kernel; up to B = --backward-max), the backward over the forward, the peak GPU memory of the
forward+backward, the deviation of the float32 Triton move from the float64 eager reference on the GPU, and that of
its gradient w.r.t. the start positions and the drag (largest error over largest entry; first 64 ropes).

    python benchmarks/speed/sim_speed.py --pegs 4 [--batches 64 1024] [--dtype float32] [--repeats 5]

With --pegs K it times instead the moves with pegs and the pin (diffdlo/planar/contact.py) on the default engine (the
C++ kernel on the CPU): K pegs of radius 1-2 cm on a 5 cm circle round the origin, among the random start shapes (those
that start clear of them: the rope's axis outside every peg), against the same moves without pegs, and the same
moves with a pin (a random node other than the grasped one) against no pin; for each B the share of ropes that
touch a peg during the move, the times of one batched move and their ratios, the time of the simulator's own check
of the pegs and the start state (torch ops, before the engine runs; "x eng": the ratio without it), and the ratio
for the forward+backward of one move. Timings are medians of --repeats interleaved runs (CPU time of the process
where the device is the CPU, so the machine's other load shows less), then a final JSON line. On a machine whose
cores are busy with other work, run it on one thread (OMP_NUM_THREADS=1): torch's threads waiting on each other
there inflate the check's time many times over.
"""
from __future__ import annotations

import argparse
import json
import resource
import statistics
import subprocess
import sys
import time

import torch

import diffdlo
from diffdlo.planar import contact


def _sync() -> None:
    if torch.cuda.is_available() and torch.cuda.is_initialized():
        torch.cuda.synchronize()


def median_time(fn, repeats: int) -> float:
    times = []
    for _ in range(repeats):
        _sync()
        t0 = time.perf_counter()
        fn()
        _sync()
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def problem(sim: diffdlo.Simulator, batch: int, seed: int = 0):
    g = torch.Generator().manual_seed(seed)
    pos = sim.random_shape(batch, g)
    node = torch.randint(0, sim.params.n_nodes, (batch,), generator=g).to(sim.device)
    delta = ((torch.rand(batch, 2, generator=g) * 2 - 1) * sim.params.action_scale).to(sim.device, sim.dtype)
    return pos, node, delta


def fb(sim, x0, n0, d0):
    """A function running the forward and backward of one move."""
    def run():
        x, d = x0.clone().requires_grad_(True), d0.clone().requires_grad_(True)
        sim.move(x, n0, d).sum().backward()
    return run


def gradients(sim, x0, n0, d0):
    """Gradients of a fixed random weighting of the moved positions w.r.t. the start positions and the drag."""
    x, d = x0.clone().requires_grad_(True), d0.clone().requires_grad_(True)
    w = torch.randn(x0.shape, generator=torch.Generator().manual_seed(1), dtype=torch.float64).to(x0.device, x0.dtype)
    return torch.autograd.grad((sim.move(x, n0, d) * w).sum(), (x, d))


def cuda_main(args) -> None:
    """--device cuda: the Triton kernel against the eager path on the GPU and the CPU C++ kernel, same inputs."""
    p = diffdlo.load_params("cable")
    tri = diffdlo.Simulator(p, device=args.device, backend="triton")
    eager = diffdlo.Simulator(p, device=args.device, backend="torch")
    reference = diffdlo.Simulator(p, device=args.device, dtype=torch.float64, backend="torch")
    cpu = diffdlo.Simulator(p)                          # auto on the CPU: the C++ kernel where it builds
    print(f"device {torch.cuda.get_device_name(tri.device)}; CPU path: "
          f"{'fused C++ kernel' if cpu.engine == 'kernel' else 'torch'} on {torch.get_num_threads()} threads")
    header = (f"{'B':>6} {'triton st/s':>12} {'eager st/s':>11} {'cpu st/s':>10} {'x eager':>8} {'x cpu':>7} "
              f"{'tri sim s/s':>11} {'cpu sim s/s':>11} {'tri f+b s':>10} {'eag f+b s':>10} {'cpu f+b s':>10} "
              f"{'bwd/fwd':>7} {'f+b MB':>8} {'dev mm':>9} {'grad dev':>9}")
    print(header)
    rows = []
    nan = float("nan")
    for batch in args.batches:
        pos, node, delta = problem(tri, batch)
        tri.move(pos[:1], node[:1], delta[:1])          # compile (first call per dtype)
        tri.integrate(pos[:1], None, 10)
        fb(tri, pos[:1], node[:1], delta[:1])()         # compile the adjoint
        t_move = median_time(lambda: tri.move(pos, node, delta), args.repeats)
        t_free = median_time(lambda: tri.integrate(pos, None, 1000), args.repeats)
        t_eager = median_time(lambda: eager.move(pos, node, delta), 1) if batch <= args.eager_max else nan
        pc, nc, dc = pos.cpu(), node.cpu(), delta.cpu()
        on_cpu = batch <= args.cpu_max
        t_cpu = median_time(lambda: cpu.move(pc, nc, dc), args.repeats) if on_cpu else nan
        t_cpu_free = median_time(lambda: cpu.integrate(pc, None, 1000), 1) if on_cpu else nan
        k = min(batch, 64)
        ref_move = reference.move(pos[:k].double(), node[:k], delta[:k].double())
        dev = (tri.move(pos[:k], node[:k], delta[:k]).double() - ref_move).norm(dim=-1).max().item() * 1000

        g_ref = gradients(reference, pos[:k].double(), node[:k], delta[:k].double())
        g_tri = gradients(tri, pos[:k], node[:k], delta[:k])
        grad_dev = max(((a.double() - b).abs().max() / b.abs().max()).item() for a, b in zip(g_tri, g_ref))
        peak_mb = nan
        if batch <= args.backward_max:
            torch.cuda.reset_peak_memory_stats(tri.device)
            before = torch.cuda.memory_allocated(tri.device)
            fb(tri, pos, node, delta)()
            peak_mb = (torch.cuda.max_memory_allocated(tri.device) - before) / 2 ** 20
        t_fb = median_time(fb(tri, pos, node, delta), args.repeats) if batch <= args.backward_max else nan
        t_fb_eager = median_time(fb(eager, pos, node, delta), 1) if batch <= min(args.eager_max, args.backward_max) \
            else nan
        t_fb_cpu = median_time(fb(cpu, pc, nc, dc), 1) if on_cpu else nan
        row = {"batch": batch, "triton_env_steps_per_s": batch / t_move, "eager_env_steps_per_s": batch / t_eager,
               "cpu_kernel_env_steps_per_s": batch / t_cpu, "triton_over_eager": t_eager / t_move,
               "triton_over_cpu": t_cpu / t_move, "triton_sim_s_per_s": 1.0 / t_free,
               "cpu_sim_s_per_s": 1.0 / t_cpu_free, "triton_forward_backward_s": t_fb,
               "eager_forward_backward_s": t_fb_eager, "cpu_forward_backward_s": t_fb_cpu,
               "triton_backward_over_forward": (t_fb - t_move) / t_move, "triton_forward_backward_peak_mb": peak_mb,
               "deviation_move_mm": dev, "gradient_relative_deviation": grad_dev}
        rows.append(row)
        print(f"{batch:>6} {row['triton_env_steps_per_s']:>12.1f} {row['eager_env_steps_per_s']:>11.1f} "
              f"{row['cpu_kernel_env_steps_per_s']:>10.1f} {row['triton_over_eager']:>7.1f}x "
              f"{row['triton_over_cpu']:>6.1f}x {row['triton_sim_s_per_s']:>11.2f} {row['cpu_sim_s_per_s']:>11.2f} "
              f"{t_fb:>10.3f} {t_fb_eager:>10.3f} {t_fb_cpu:>10.3f} {row['triton_backward_over_forward']:>7.2f} "
              f"{peak_mb:>8.0f} {dev:>9.2e} {grad_dev:>9.1e}", flush=True)
    print(json.dumps({"device": str(tri.device), "gpu": torch.cuda.get_device_name(tri.device),
                      "threads": torch.get_num_threads(), "rows": rows}))


def ring_pegs(n_pegs: int, dtype=torch.float32) -> torch.Tensor:
    """(K, 3) pegs of radius 1 to 2 cm on a 5 cm circle round the origin, where the random start shapes lie."""
    angle = torch.arange(n_pegs, dtype=torch.float64) * (2 * torch.pi / n_pegs) + 0.3
    radius = torch.linspace(0.01, 0.02, n_pegs, dtype=torch.float64)
    return torch.stack([0.05 * angle.cos(), 0.05 * angle.sin(), radius], -1).to(dtype)


def peg_problem(sim: diffdlo.Simulator, batch: int, pegs: torch.Tensor, seed: int = 0):
    """Random start shapes that start clear of ``pegs`` (the rope's surface at most half its radius into a peg;
    the others are drawn again), random actions as ``problem``'s, and a random pin other than the grasped node."""
    p = sim.params
    g = torch.Generator().manual_seed(seed)
    kept, count = [], 0
    for _ in range(100):
        if count >= batch:
            break
        shapes = sim.random_shape(batch, g)
        ok = contact.depth(shapes, pegs.to(shapes).expand(batch, *pegs.shape), p.rope_radius) <= 0.5 * p.rope_radius
        kept.append(shapes[ok])
        count += int(ok.sum())
    else:
        raise SystemExit(f"only {count} of 100 x {batch} random shapes start clear of the {len(pegs)} pegs; use fewer")
    pos = torch.cat(kept)[:batch]
    node = torch.randint(0, p.n_nodes, (batch,), generator=g).to(sim.device)
    delta = ((torch.rand(batch, 2, generator=g) * 2 - 1) * p.action_scale).to(sim.device, sim.dtype)
    pin = torch.randint(0, p.n_nodes, (batch,), generator=g).to(sim.device)
    pin = torch.where(pin == node, (pin + 1) % p.n_nodes, pin)
    return pos, node, delta, pin


def interleaved_medians(fns: dict, repeats: int, clock=time.perf_counter) -> dict:
    """Median time of each function over ``repeats`` rounds that run them all in turn (drifts of the machine's
    load hit them alike)."""
    times = {key: [] for key in fns}
    for fn in fns.values():                      # warm-up: first-call allocations and caches
        fn()
    for _ in range(repeats):
        for key, fn in fns.items():
            _sync()
            t0 = clock()
            fn()
            _sync()
            times[key].append(clock() - t0)
    return {key: statistics.median(values) for key, values in times.items()}


def pegs_main(args) -> None:
    """--pegs K: moves with K pegs and with a pin against the same moves without, on the default engine."""
    dtype = {"float32": torch.float32, "float64": torch.float64}[args.dtype]
    sim = diffdlo.Simulator(diffdlo.load_params("cable"), device=args.device, dtype=dtype)
    pegs = ring_pegs(args.pegs, dtype).to(sim.device)
    on_cpu = sim.device.type == "cpu"
    clock = time.process_time if on_cpu else time.perf_counter
    print(f"moves with {args.pegs} pegs (radius 1-2 cm, 5 cm round the origin) and a pin: engine "
          f"{sim.contact_engine} (without: {sim.engine}) on {sim.device}, {args.dtype}, "
          f"{torch.get_num_threads()} threads; {'CPU' if on_cpu else 'wall'} time, median of {args.repeats}")
    print(f"{'B':>6} {'touch':>6} {'move ms':>9} {'pegs ms':>9} {'x':>6} {'check ms':>9} {'x eng':>6} {'pin ms':>9} "
          f"{'x':>6} {'f+b ms':>9} {'pegs f+b':>9} {'x':>6}")
    rows = []
    for batch in args.batches:
        pos, node, delta, pin = peg_problem(sim, batch, pegs)
        _, info = sim.move(pos, node, delta, pegs, return_info=True, record_every=20)
        touch = float(torch.stack([contact.depth(f, pegs.expand(batch, *pegs.shape), sim.params.rope_radius)
                                   for f in info.frames]).gt(0).any(0).float().mean())

        def fb(with_pegs):
            def run():
                x, d = pos.clone().requires_grad_(True), delta.clone().requires_grad_(True)
                sim.move(x, node, d, pegs if with_pegs else None).sum().backward()
            return run

        t = interleaved_medians({"move": lambda: sim.move(pos, node, delta),
                                 "pegs": lambda: sim.move(pos, node, delta, pegs),
                                 "check": lambda: sim._check_pegs(pos, pegs),      # what move runs before the engine
                                 "pin": lambda: sim.move(pos, node, delta, None, pin)}, args.repeats, clock)
        t.update(interleaved_medians({"fb": fb(False), "fb_pegs": fb(True)}, max(1, args.repeats // 2), clock))
        row = {"batch": batch, "touching": touch, "move_s": t["move"], "pegs_move_s": t["pegs"],
               "pegs_over_plain": t["pegs"] / t["move"], "pegs_check_s": t["check"],
               "pegs_engine_over_plain": (t["pegs"] - t["check"]) / t["move"],
               "pin_move_s": t["pin"], "pin_over_plain": t["pin"] / t["move"],
               "forward_backward_s": t["fb"], "pegs_forward_backward_s": t["fb_pegs"],
               "pegs_forward_backward_over_plain": t["fb_pegs"] / t["fb"]}
        rows.append(row)
        print(f"{batch:>6} {touch:>6.0%} {t['move'] * 1e3:>9.2f} {t['pegs'] * 1e3:>9.2f} "
              f"{row['pegs_over_plain']:>5.2f}x {t['check'] * 1e3:>9.2f} {row['pegs_engine_over_plain']:>5.2f}x "
              f"{t['pin'] * 1e3:>9.2f} {row['pin_over_plain']:>5.2f}x "
              f"{t['fb'] * 1e3:>9.1f} {t['fb_pegs'] * 1e3:>9.1f} {row['pegs_forward_backward_over_plain']:>5.2f}x",
              flush=True)
    print(json.dumps({"device": str(sim.device), "dtype": args.dtype, "threads": torch.get_num_threads(),
                      "pegs": args.pegs, "engine": sim.contact_engine, "rows": rows}))


def memory_probe(batch: int, moves: int, backend: str) -> dict:
    """Peak RSS growth [MB] while taking the gradient of a `moves`-move sequence (run in a fresh process)."""
    sim = diffdlo.Simulator(diffdlo.load_params("cable"), backend=backend)
    pos, node, delta = problem(sim, batch)
    target = sim.target_shape("diagonal")
    deltas = delta.unsqueeze(0).repeat(moves, 1, 1).requires_grad_(True)
    start = pos.clone().requires_grad_(True)
    base = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    t0 = time.perf_counter()
    x = start
    for m in range(moves):
        x = sim.move(x, node, deltas[m] * 0.5)
    diffdlo.shape_error(x, target).sum().backward()
    wall = time.perf_counter() - t0
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    return {"batch": batch, "moves": moves, "backend": backend, "peak_rss_growth_mb": peak - base,
            "peak_rss_mb": peak, "wall_s": wall, "grad_norm": float(deltas.grad.norm()),
            "grad_finite": bool(torch.isfinite(deltas.grad).all() and torch.isfinite(start.grad).all())}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--batches", type=int, nargs="+", default=[1, 64, 1024])
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--memory-batch", type=int, default=256)
    parser.add_argument("--memory-moves", type=int, default=10)
    parser.add_argument("--eager-max", type=int, default=1024, help="cuda: largest B timed on the eager path")
    parser.add_argument("--cpu-max", type=int, default=65536, help="cuda: largest B timed on the CPU kernel")
    parser.add_argument("--backward-max", type=int, default=65536,
                        help="cuda: largest B whose forward+backward is timed")
    parser.add_argument("--pegs", type=int, default=0,
                        help="time moves with this many pegs and with a pin against plain moves instead")
    parser.add_argument("--dtype", choices=("float32", "float64"), default="float32", help="--pegs: the state's dtype")
    parser.add_argument("--_memory_probe", action="store_true", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.pegs < 0:
        parser.error(f"--pegs must be >= 0, got {args.pegs}")
    if args.pegs > 0:
        pegs_main(args)
        return
    if args.device.startswith("cuda") and not args._memory_probe:
        cuda_main(args)
        return
    if args._memory_probe:
        print(json.dumps(memory_probe(args.memory_batch, args.memory_moves, "auto")))
        return

    p = diffdlo.load_params("cable")
    fast = diffdlo.Simulator(p, device=args.device)
    eager = diffdlo.Simulator(p, device=args.device, backend="torch")
    reference = diffdlo.Simulator(p, device=args.device, dtype=torch.float64, backend="torch")
    print(f"default path: {'fused C++ kernel' if fast.engine == 'kernel' else 'torch'} on {fast.device}, "
          f"{torch.get_num_threads()} threads")
    header = (f"{'B':>6} {'env steps/s':>12} {'eager':>9} {'ratio':>7} {'sim s/s':>9} {'eager':>8} {'ratio':>7} "
              f"{'dev move mm':>11} {'dev free mm':>11} {'bwd/fwd':>8}")
    print(header)
    rows = []
    for batch in args.batches:
        pos, node, delta = problem(fast, batch)
        t_move = median_time(lambda: fast.move(pos, node, delta), args.repeats)
        t_move_eager = median_time(lambda: eager.move(pos, node, delta), 1)
        t_free = median_time(lambda: fast.integrate(pos, None, 1000), args.repeats)
        t_free_eager = median_time(lambda: eager.integrate(pos, None, 1000), 1)
        k = min(batch, 64)
        ref_move = reference.move(pos[:k].double(), node[:k], delta[:k].double())
        dev_move = (fast.move(pos[:k], node[:k], delta[:k]).double() - ref_move).norm(dim=-1).max().item() * 1000
        ref_free = reference.integrate(pos[:k].double(), None, 1000)[0]
        dev_free = (fast.integrate(pos[:k], None, 1000)[0].double() - ref_free).norm(dim=-1).max().item() * 1000
        x, d = pos.clone().requires_grad_(True), delta.clone().requires_grad_(True)

        def forward_backward():
            fast.move(x, node, d).sum().backward()

        t_fb = median_time(forward_backward, args.repeats)
        row = {"batch": batch, "env_steps_per_s": batch / t_move, "eager_env_steps_per_s": batch / t_move_eager,
               "ratio_env_steps": t_move_eager / t_move, "sim_s_per_s": 1.0 / t_free,
               "eager_sim_s_per_s": 1.0 / t_free_eager, "ratio_sim_s": t_free_eager / t_free,
               "deviation_move_mm": dev_move, "deviation_free_mm": dev_free,
               "backward_over_forward": (t_fb - t_move) / t_move}
        rows.append(row)
        print(f"{batch:>6} {row['env_steps_per_s']:>12.1f} {row['eager_env_steps_per_s']:>9.2f} "
              f"{row['ratio_env_steps']:>6.0f}x {row['sim_s_per_s']:>9.2f} {row['eager_sim_s_per_s']:>8.3f} "
              f"{row['ratio_sim_s']:>6.0f}x {dev_move:>11.2e} {dev_free:>11.2e} {row['backward_over_forward']:>8.2f}",
              flush=True)
    probe = subprocess.run([sys.executable, __file__, "--_memory_probe", "--memory-batch", str(args.memory_batch),
                            "--memory-moves", str(args.memory_moves)], capture_output=True, text=True, check=True)
    memory = json.loads(probe.stdout.strip().splitlines()[-1])
    print(f"gradient of a {memory['moves']}-move sequence at B={memory['batch']}: peak memory growth "
          f"{memory['peak_rss_growth_mb']:.0f} MB (process peak {memory['peak_rss_mb']:.0f} MB), "
          f"{memory['wall_s']:.1f} s, gradient finite: {memory['grad_finite']}")
    print(json.dumps({"device": str(fast.device), "threads": torch.get_num_threads(), "rows": rows,
                      "memory": memory}))


if __name__ == "__main__":
    main()
