// Fused CPU kernel of the 3-D chain's gripper move, forward only: the grippers' path (diffdlo/chain3d/grippers.py
// move), then the hold until the cable is at rest (grippers.py settle), each frame of the chain's semi-implicit Euler
// substeps (diffdlo/chain3d/chain.py rollout and _forces: stretching, discrete bending, gravity, the floor, axial and
// bending Kelvin-Voigt damping, the implicit drag). Plain C++ with a C ABI, called through ctypes on tensor data
// (diffdlo/chain3d/kernel.py); the eager torch path is the reference and the test oracle, and this file mirrors it
// step by step. Gradients are not computed here: a move that needs them runs the eager path, whose autograd carries
// them (the planners' CEM and the env step need none).
//
// Chains run in lane groups of W: a group's state is laid out [node][axis][lane], so every inner loop runs over the
// W lanes and vectorizes (16 floats = one AVX-512 vector). A batch that is not a multiple of W fills its last group
// with copies of its last chain (computed, never returned). Groups run in parallel on a few std::threads taking
// groups from an atomic counter (not OpenMP: its spinning idle threads would fight PyTorch's own runtime). A group
// steps until all its lanes are at rest or at the cap; a lane's state is copied out when it comes to rest (as the
// eager settle freezes it), so a lane never depends on the others.
#include <algorithm>
#include <atomic>
#include <cmath>
#include <cstdint>
#include <thread>
#include <vector>

namespace {

constexpr int W = 16;
constexpr double TINY = 1e-12;    // chain.py _TINY: below this sin(theta) a node's bending plane is undefined

template <typename F>
void parallel_for(int64_t count, int64_t threads, F body) {
  const int64_t workers = std::max<int64_t>(1, std::min(threads, count));
  if (workers == 1) {
    for (int64_t i = 0; i < count; ++i) body(i);
    return;
  }
  std::atomic<int64_t> next{0};
  auto work = [&]() {
    for (int64_t i = next.fetch_add(1); i < count; i = next.fetch_add(1)) body(i);
  };
  std::vector<std::thread> pool;
  for (int64_t t = 1; t < workers; ++t) pool.emplace_back(work);
  work();
  for (auto& t : pool) t.join();
}

// ip[] from Python, in this order. path_frames = move frames + 1 (1: a settle alone).
struct Ints {
  int64_t B, n, n_held, substeps, path_frames, check_frames, settle_frames, threads;
};
// fp[] from Python, in this order.
struct Reals {
  double frame_dt, rest_speed, divergence_radius;
};
// Per chain, phys[b] holds (N-1) rest lengths, N masses, N drag coefficients c_d lambda_j, then these 9 scalars.
enum Scalar { EI, EA, AXIAL, BENDING, GRAVITY, FLOOR_Z, FLOOR_K, FLOOR_C, FLOOR_W, N_SCALARS };

inline int64_t phys_width(int64_t n) { return (n - 1) + 2 * n + N_SCALARS; }

template <typename T>
struct Group {
  int64_t n;
  std::vector<T> x, v, f, g;                 // [node][axis][lane]: positions, velocities, forces; g: per link
  std::vector<T> rest, voronoi, h_over_m, damp, weight;    // [link or node][lane]
  std::vector<T> s;                          // [scalar][lane]
  std::vector<T> start, end, hold;           // [held][axis][lane]: this frame's path, the settle's hold
  explicit Group(int64_t n_, int64_t n_held)
      : n(n_), x(n_ * 3 * W), v(n_ * 3 * W), f(n_ * 3 * W), g(n_ * 3 * W), rest((n_ - 1) * W),
        voronoi((n_ - 2) * W), h_over_m(n_ * W), damp(n_ * W), weight(n_ * W), s(N_SCALARS * W),
        start(n_held * 3 * W), end(n_held * 3 * W), hold(n_held * 3 * W) {}
  T* at(std::vector<T>& a, int64_t j, int d) { return a.data() + (j * 3 + d) * W; }
};

// One substep of every lane: F(x, v) without the drag, then v+ = (v + h F / m) / (1 + h c_d lambda / m),
// x+ = x + h v+ (chain.py rollout), then the held nodes put on the path at alpha of the frame.
template <typename T>
void substep(Group<T>& G, const int64_t* held, int64_t n_held, T h, T alpha, const T* vh) {
  const int64_t n = G.n;
  std::fill(G.g.begin(), G.g.end(), T(0));
  T* s = G.s.data();
  const T* ei = s + EI * W; const T* ea = s + EA * W; const T* eta_a = s + AXIAL * W; const T* eta_b = s + BENDING * W;
  // links: the stretching gradient and the axial damping's dR/d(de/dt), into g[k]
  std::vector<T>& x = G.x; std::vector<T>& v = G.v;
  for (int64_t k = 0; k < n - 1; ++k) {
    T* gx = G.at(G.g, k, 0); T* gy = G.at(G.g, k, 1); T* gz = G.at(G.g, k, 2);
    const T* x0 = G.at(x, k, 0); const T* y0 = G.at(x, k, 1); const T* z0 = G.at(x, k, 2);
    const T* x1 = G.at(x, k + 1, 0); const T* y1 = G.at(x, k + 1, 1); const T* z1 = G.at(x, k + 1, 2);
    const T* vx0 = G.at(v, k, 0); const T* vy0 = G.at(v, k, 1); const T* vz0 = G.at(v, k, 2);
    const T* vx1 = G.at(v, k + 1, 0); const T* vy1 = G.at(v, k + 1, 1); const T* vz1 = G.at(v, k + 1, 2);
    const T* r = G.rest.data() + k * W;
    for (int l = 0; l < W; ++l) {
      const T ex = x1[l] - x0[l], ey = y1[l] - y0[l], ez = z1[l] - z0[l];
      const T L = std::sqrt(ex * ex + ey * ey + ez * ez);
      const T nx = ex / L, ny = ey / L, nz = ez / L;
      const T rate = nx * (vx1[l] - vx0[l]) + ny * (vy1[l] - vy0[l]) + nz * (vz1[l] - vz0[l]);
      const T coef = ea[l] / r[l] * (L - r[l]) + eta_a[l] / r[l] * rate;
      gx[l] = coef * nx; gy[l] = coef * ny; gz[l] = coef * nz;
    }
  }
  // interior nodes i + 1 (links a = i, b = i + 1): bending's dE/de and the bending damping's dR/d(de/dt)
  for (int64_t i = 0; i < n - 2; ++i) {
    const T* D = G.voronoi.data() + i * W;
    T* __restrict gax = G.at(G.g, i, 0); T* __restrict gay = G.at(G.g, i, 1); T* __restrict gaz = G.at(G.g, i, 2);
    T* __restrict gbx = G.at(G.g, i + 1, 0); T* __restrict gby = G.at(G.g, i + 1, 1);
    T* __restrict gbz = G.at(G.g, i + 1, 2);
    const T* x0 = G.at(x, i, 0); const T* y0 = G.at(x, i, 1); const T* z0 = G.at(x, i, 2);
    const T* x1 = G.at(x, i + 1, 0); const T* y1 = G.at(x, i + 1, 1); const T* z1 = G.at(x, i + 1, 2);
    const T* x2 = G.at(x, i + 2, 0); const T* y2 = G.at(x, i + 2, 1); const T* z2 = G.at(x, i + 2, 2);
    const T* u0 = G.at(v, i, 0); const T* w0 = G.at(v, i, 1); const T* q0 = G.at(v, i, 2);
    const T* u1 = G.at(v, i + 1, 0); const T* w1 = G.at(v, i + 1, 1); const T* q1 = G.at(v, i + 1, 2);
    const T* u2 = G.at(v, i + 2, 0); const T* w2 = G.at(v, i + 2, 1); const T* q2 = G.at(v, i + 2, 2);
#pragma GCC ivdep
    for (int l = 0; l < W; ++l) {
      T ax = x1[l] - x0[l], ay = y1[l] - y0[l], az = z1[l] - z0[l];         // link a = i, b = i + 1
      T bx = x2[l] - x1[l], by = y2[l] - y1[l], bz = z2[l] - z1[l];
      const T rax = u1[l] - u0[l], ray = w1[l] - w0[l], raz = q1[l] - q0[l];  // their rates
      const T rbx = u2[l] - u1[l], rby = w2[l] - w1[l], rbz = q2[l] - q1[l];
      const T la = std::sqrt(ax * ax + ay * ay + az * az);
      const T lb = std::sqrt(bx * bx + by * by + bz * bz);
      ax /= la; ay /= la; az /= la;
      bx /= lb; by /= lb; bz /= lb;
      const T c = ax * bx + ay * by + az * bz;
      const T pax = bx - c * ax, pay = by - c * ay, paz = bz - c * az;      // b^ - c a^ (_|_ a)
      const T pbx = ax - c * bx, pby = ay - c * by, pbz = az - c * bz;      // a^ - c b^ (_|_ b)
      const T one_c = T(1) + c;
      const T dE_dc = -T(4) * ei[l] / (D[l] * one_c * one_c);
      // bending damping: the unit normals in the links' plane (zero where the links are parallel)
      const T na2 = pax * pax + pay * pay + paz * paz;
      const T nb2 = pbx * pbx + pby * pby + pbz * pbz;
      const T tiny2 = T(TINY * TINY);
      const T ia = na2 > tiny2 ? T(1) / std::sqrt(std::max(na2, tiny2)) : T(0);
      const T ib = nb2 > tiny2 ? T(1) / std::sqrt(std::max(nb2, tiny2)) : T(0);
      const T tax = pax * ia / la, tay = pay * ia / la, taz = paz * ia / la;
      const T tbx = pbx * ib / lb, tby = pby * ib / lb, tbz = pbz * ib / lb;
      const T ds = T(2) / one_c;
      const T bend_rate = -ds * (tax * rax + tay * ray + taz * raz + tbx * rbx + tby * rby + tbz * rbz);
      const T scale = -eta_b[l] / D[l] * bend_rate * ds;
      gax[l] += dE_dc * pax / la + scale * tax;
      gay[l] += dE_dc * pay / la + scale * tay;
      gaz[l] += dE_dc * paz / la + scale * taz;
      gbx[l] += dE_dc * pbx / lb + scale * tbx;
      gby[l] += dE_dc * pby / lb + scale * tby;
      gbz[l] += dE_dc * pbz / lb + scale * tbz;
    }
  }
  // nodes: F_j = g_j - g_{j-1} (chain.py _to_nodes), minus the weight, the floor's push and its dashpot
  const T* zf = s + FLOOR_Z * W; const T* kf = s + FLOOR_K * W; const T* cf = s + FLOOR_C * W;
  const T* wf = s + FLOOR_W * W;
  for (int64_t j = 0; j < n; ++j) {
    const T* hm = G.h_over_m.data() + j * W; const T* dp = G.damp.data() + j * W;
    const T* wt = G.weight.data() + j * W;
    for (int d = 0; d < 3; ++d) {
      T* vd = G.at(v, j, d);
      const T* gj = j < n - 1 ? G.at(G.g, j, d) : nullptr;
      const T* gp = j > 0 ? G.at(G.g, j - 1, d) : nullptr;
      const T* z = G.at(x, j, 2); const T* vz = G.at(v, j, 2);
      for (int l = 0; l < W; ++l) {
        T F = (gj ? gj[l] : T(0)) - (gp ? gp[l] : T(0));
        if (d == 2) {
          const T zp = std::max(zf[l] - z[l], T(0));
          const bool ramp = zp < wf[l];
          const T push = ramp ? zp * zp / (T(2) * wf[l]) : zp - T(0.5) * wf[l];
          const T onset = ramp ? zp / wf[l] : T(1);
          F -= wt[l] - kf[l] * push + cf[l] * onset * vz[l];
        }
        vd[l] = (vd[l] + hm[l] * F) * dp[l];
      }
    }
    for (int d = 0; d < 3; ++d) {
      T* xd = G.at(x, j, d); const T* vd = G.at(v, j, d);
      for (int l = 0; l < W; ++l) xd[l] += h * vd[l];
    }
  }
  for (int64_t q = 0; q < n_held; ++q) {
    for (int d = 0; d < 3; ++d) {
      T* xd = G.at(x, held[q], d); T* vd = G.at(v, held[q], d);
      const T* a = G.start.data() + (q * 3 + d) * W; const T* b = G.end.data() + (q * 3 + d) * W;
      const T* u = vh + (q * 3 + d) * W;
      for (int l = 0; l < W; ++l) { xd[l] = (T(1) - alpha) * a[l] + alpha * b[l]; vd[l] = u[l]; }
    }
  }
}

// A lane group's chains, loaded: parameters, the start state, the hold; the path read per frame.
template <typename T>
struct Run {
  const Ints& in;
  const Reals& re;
  const int64_t group, n, H, B, move_frames;
  const int64_t* held;
  const T* path;
  const T h, dt;
  int64_t lane_b[W];          // the batch row of each lane (the last row again past the batch's end)
  Group<T> G;
  std::vector<T> vh;          // [held][axis][lane] the held nodes' velocity over the current frame

  Run(const Ints& in_, const Reals& re_, int64_t group_, const int64_t* held_, const T* x0, const T* v0,
      const T* path_, const T* hold, const T* phys)
      : in(in_), re(re_), group(group_), n(in_.n), H(in_.n_held), B(in_.B), move_frames(in_.path_frames - 1),
        held(held_), path(path_), h(T(re_.frame_dt / in_.substeps)), dt(T(re_.frame_dt)), G(in_.n, in_.n_held),
        vh(in_.n_held * 3 * W, T(0)) {
    for (int l = 0; l < W; ++l) lane_b[l] = std::min(group * W + l, B - 1);
    const int64_t P = phys_width(n);
    for (int l = 0; l < W; ++l) {
      const T* p = phys + lane_b[l] * P;
      for (int64_t k = 0; k < n - 1; ++k) G.rest[k * W + l] = p[k];
      for (int64_t i = 0; i < n - 2; ++i) G.voronoi[i * W + l] = T(0.5) * (p[i] + p[i + 1]);
      const T* mass = p + (n - 1); const T* drag = mass + n; const T* sc = drag + n;
      for (int64_t j = 0; j < n; ++j) {
        G.h_over_m[j * W + l] = h / mass[j];
        G.damp[j * W + l] = T(1) / (T(1) + h * drag[j] / mass[j]);
        G.weight[j * W + l] = mass[j] * sc[GRAVITY];
      }
      for (int q = 0; q < N_SCALARS; ++q) G.s[q * W + l] = sc[q];
      for (int64_t j = 0; j < n; ++j)
        for (int d = 0; d < 3; ++d) {
          G.x[(j * 3 + d) * W + l] = x0[(lane_b[l] * n + j) * 3 + d];
          G.v[(j * 3 + d) * W + l] = v0 ? v0[(lane_b[l] * n + j) * 3 + d] : T(0);
        }
      for (int64_t q = 0; q < H; ++q)
        for (int d = 0; d < 3; ++d) G.hold[(q * 3 + d) * W + l] = hold[(lane_b[l] * H + q) * 3 + d];
    }
  }
  // the path's frame k into dst [held][axis][lane]
  void path_frame(int64_t k, std::vector<T>& dst) const {
    for (int l = 0; l < W; ++l)
      for (int64_t q = 0; q < H; ++q)
        for (int d = 0; d < 3; ++d) dst[(q * 3 + d) * W + l] = path[((k * B + lane_b[l]) * H + q) * 3 + d];
  }
  // frame 0: the held nodes on the path's first frame, with its first velocity (chain.py rollout)
  void start() {
    path_frame(0, G.start);
    if (in.path_frames > 1) path_frame(1, G.end); else G.end = G.start;
    for (int64_t q = 0; q < H; ++q)
      for (int d = 0; d < 3; ++d)
        for (int l = 0; l < W; ++l) {
          const int64_t o = (q * 3 + d) * W + l;
          G.x[(held[q] * 3 + d) * W + l] = G.start[o];
          G.v[(held[q] * 3 + d) * W + l] = in.path_frames > 1 ? (G.end[o] - G.start[o]) / dt : T(0);
        }
  }
  // frame k's start: its path segment (the hold once the move is over), the held nodes' velocity over it, and the
  // held nodes put on its start (where the last substep left them)
  void begin_frame(int64_t k) {
    if (k <= move_frames) { path_frame(k - 1, G.start); path_frame(k, G.end); }
    else { G.start = G.hold; G.end = G.hold; }
    for (int64_t q = 0; q < H; ++q)
      for (int d = 0; d < 3; ++d)
        for (int l = 0; l < W; ++l) {
          const int64_t o = (q * 3 + d) * W + l;
          vh[o] = (G.end[o] - G.start[o]) / dt;
          G.v[(held[q] * 3 + d) * W + l] = vh[o];
          G.x[(held[q] * 3 + d) * W + l] = G.start[o];
        }
  }
  T alpha(int64_t s) const { return T(double(s) / double(in.substeps)); }
  void frame(int64_t k) {
    begin_frame(k);
    for (int64_t s = 1; s <= in.substeps; ++s) substep(G, held, H, h, alpha(s), vh.data());
  }
};

template <typename T>
void run_group(const Ints& in, const Reals& re, int64_t group, const int64_t* held, const T* x0, const T* v0,
               const T* path, const T* hold, const T* phys, T* x_out, T* v_out, uint8_t* settled, int64_t* frames,
               int64_t* diverged) {
  Run<T> R(in, re, group, held, x0, v0, path, hold, phys);
  Group<T>& G = R.G;
  const int64_t n = in.n, H = in.n_held, B = in.B;
  bool done[W];
  for (int l = 0; l < W; ++l) done[l] = false;
  auto finish = [&](int l, bool at_rest, int64_t frame) {
    done[l] = true;
    const int64_t b = group * W + l;
    if (b >= B) return;
    for (int64_t j = 0; j < n; ++j)
      for (int d = 0; d < 3; ++d) {
        x_out[(b * n + j) * 3 + d] = G.x[(j * 3 + d) * W + l];
        v_out[(b * n + j) * 3 + d] = G.v[(j * 3 + d) * W + l];
      }
    settled[b] = at_rest;
    frames[b] = frame;
  };
  R.start();
  const int64_t last = R.move_frames + in.settle_frames;
  const T radius = T(re.divergence_radius);
  for (int64_t k = 1; k <= last; ++k) {
    R.frame(k);
    // a non-finite or runaway state: report the frame, stop the lane
    for (int l = 0; l < W; ++l) {
      if (done[l]) continue;
      bool bad = false;
      for (int64_t j = 0; j < n; ++j)
        for (int d = 0; d < 3; ++d) {
          const T value = G.x[(j * 3 + d) * W + l];
          bad = bad || !std::isfinite(value) || std::abs(value) > radius;
        }
      if (bad) {
        if (group * W + l < B) diverged[group * W + l] = k;
        finish(l, false, k);
      }
    }
    const int64_t into_settle = k - R.move_frames;
    if (into_settle >= 1 && (into_settle % in.check_frames == 0 || k == last)) {
      // grippers.py settle: at rest when the free nodes' fastest speed is below rest_speed
      for (int l = 0; l < W; ++l) {
        if (done[l]) continue;
        T fastest = T(0);
        for (int64_t j = 0, q = 0; j < n; ++j) {
          if (q < H && held[q] == j) { ++q; continue; }
          T sq = T(0);
          for (int d = 0; d < 3; ++d) { const T u = G.v[(j * 3 + d) * W + l]; sq += u * u; }
          fastest = std::max(fastest, std::sqrt(sq));
        }
        if (fastest < T(re.rest_speed)) finish(l, true, k);
        else if (k == last) finish(l, false, k);
      }
    }
    bool all = true;
    for (int l = 0; l < W; ++l) all = all && done[l];
    if (all) break;
  }
  for (int l = 0; l < W; ++l)     // no settle at all (settle_frames = 0): the move's end, not at rest
    if (!done[l]) finish(l, false, last);
}

// ---------------------------------------------------------------------------------------------------- the adjoint
// The reverse of one substep, at the state G.x, G.v before it: (gx, gv), the gradient w.r.t. the state after it,
// becomes the gradient w.r.t. the state before it, and the held nodes' overwrite adds to the gradients w.r.t. the
// frame's path segment (gs: its start, ge: its end, gvh: the held velocity). Each line reverses a line of
// ``substep`` (reverse-mode by hand; the tests hold it against autograd of the eager chain).
template <typename T>
void substep_backward(Group<T>& G, const int64_t* held, int64_t n_held, T h, T alpha, T* gx, T* gv, T* gs, T* ge,
                      T* gvh, T* gF, T* gG) {
  const int64_t n = G.n;
  const std::vector<T>& x = G.x; const std::vector<T>& v = G.v;
  auto X = [&](int64_t j, int d) { return x.data() + (j * 3 + d) * W; };
  auto V = [&](int64_t j, int d) { return v.data() + (j * 3 + d) * W; };
  auto A = [](T* a, int64_t j, int d) { return a + (j * 3 + d) * W; };
  // the held nodes' overwrite: x = (1 - alpha) start + alpha end, v = vh
  for (int64_t q = 0; q < n_held; ++q)
    for (int d = 0; d < 3; ++d) {
      T* gxd = A(gx, held[q], d); T* gvd = A(gv, held[q], d);
      T* s = gs + (q * 3 + d) * W; T* e = ge + (q * 3 + d) * W; T* u = gvh + (q * 3 + d) * W;
      for (int l = 0; l < W; ++l) {
        s[l] += (T(1) - alpha) * gxd[l]; e[l] += alpha * gxd[l]; u[l] += gvd[l];
        gxd[l] = T(0); gvd[l] = T(0);
      }
    }
  // x+ = x + h v+ ; v+ = (v + h/m F) damp  ->  gF = (gv + h gx) damp h/m, gv <- (gv + h gx) damp
  for (int64_t j = 0; j < n; ++j) {
    const T* hm = G.h_over_m.data() + j * W; const T* dp = G.damp.data() + j * W;
    for (int d = 0; d < 3; ++d) {
      const T* gxd = A(gx, j, d); T* gvd = A(gv, j, d); T* gf = A(gF, j, d);
      for (int l = 0; l < W; ++l) {
        const T pre = (gvd[l] + h * gxd[l]) * dp[l];
        gvd[l] = pre;
        gf[l] = pre * hm[l];
      }
    }
  }
  // F_j = g_j - g_{j-1} - (weight - k_f push + c_f onset v_z)_j e_z
  const T* s = G.s.data();
  const T* zf = s + FLOOR_Z * W; const T* kf = s + FLOOR_K * W; const T* cf = s + FLOOR_C * W;
  const T* wf = s + FLOOR_W * W;
  for (int64_t j = 0; j < n; ++j) {
    const T* z = X(j, 2); const T* vz = V(j, 2); const T* gf = A(gF, j, 2);
    T* gxz = A(gx, j, 2); T* gvz = A(gv, j, 2);
    for (int l = 0; l < W; ++l) {
      const T depth = zf[l] - z[l];
      const T zp = std::max(depth, T(0));
      const bool ramp = zp < wf[l];
      const T onset = ramp ? zp / wf[l] : T(1);
      const T donset = (ramp && depth > T(0)) ? T(1) / wf[l] : T(0);     // d onset / d(-z)
      gxz[l] += gf[l] * (-kf[l] * onset + cf[l] * vz[l] * donset);
      gvz[l] += gf[l] * (-cf[l] * onset);
    }
  }
  for (int64_t k = 0; k < n - 1; ++k)
    for (int d = 0; d < 3; ++d) {
      T* gg = A(gG, k, d); const T* f0 = A(gF, k, d); const T* f1 = A(gF, k + 1, d);
      for (int l = 0; l < W; ++l) gg[l] = f0[l] - f1[l];
    }
  // the links' terms: g_k = (EA / r (L - r) + eta_A / r n.rate) n, n = e / L
  const T* ea = s + EA * W; const T* eta_a = s + AXIAL * W; const T* ei = s + EI * W; const T* eta_b = s + BENDING * W;
  for (int64_t k = 0; k < n - 1; ++k) {
    const T* x0 = X(k, 0); const T* y0 = X(k, 1); const T* z0 = X(k, 2);
    const T* x1 = X(k + 1, 0); const T* y1 = X(k + 1, 1); const T* z1 = X(k + 1, 2);
    const T* u0 = V(k, 0); const T* w0 = V(k, 1); const T* q0 = V(k, 2);
    const T* u1 = V(k + 1, 0); const T* w1 = V(k + 1, 1); const T* q1 = V(k + 1, 2);
    const T* gg0 = A(gG, k, 0); const T* gg1 = A(gG, k, 1); const T* gg2 = A(gG, k, 2);
    T* ax0 = A(gx, k, 0); T* ay0 = A(gx, k, 1); T* az0 = A(gx, k, 2);
    T* ax1 = A(gx, k + 1, 0); T* ay1 = A(gx, k + 1, 1); T* az1 = A(gx, k + 1, 2);
    T* bx0 = A(gv, k, 0); T* by0 = A(gv, k, 1); T* bz0 = A(gv, k, 2);
    T* bx1 = A(gv, k + 1, 0); T* by1 = A(gv, k + 1, 1); T* bz1 = A(gv, k + 1, 2);
    const T* r = G.rest.data() + k * W;
#pragma GCC ivdep
    for (int l = 0; l < W; ++l) {
      const T ex = x1[l] - x0[l], ey = y1[l] - y0[l], ez = z1[l] - z0[l];
      const T rx = u1[l] - u0[l], ry = w1[l] - w0[l], rz = q1[l] - q0[l];
      const T L = std::sqrt(ex * ex + ey * ey + ez * ez);
      const T nx = ex / L, ny = ey / L, nz = ez / L;
      const T rate = nx * rx + ny * ry + nz * rz;
      const T coef = ea[l] / r[l] * (L - r[l]) + eta_a[l] / r[l] * rate;
      const T gcoef = gg0[l] * nx + gg1[l] * ny + gg2[l] * nz;
      T gnx = coef * gg0[l], gny = coef * gg1[l], gnz = coef * gg2[l];
      T gL = ea[l] / r[l] * gcoef;
      const T grate = eta_a[l] / r[l] * gcoef;
      gnx += grate * rx; gny += grate * ry; gnz += grate * rz;
      const T grx = grate * nx, gry = grate * ny, grz = grate * nz;
      gL -= (gnx * nx + gny * ny + gnz * nz) / L;
      const T gex = gnx / L + gL * nx, gey = gny / L + gL * ny, gez = gnz / L + gL * nz;
      ax1[l] += gex; ay1[l] += gey; az1[l] += gez; ax0[l] -= gex; ay0[l] -= gey; az0[l] -= gez;
      bx1[l] += grx; by1[l] += gry; bz1[l] += grz; bx0[l] -= grx; by0[l] -= gry; bz0[l] -= grz;
    }
  }
  // the bending terms at interior node i + 1 (links a = i, b = i + 1): substep's lines reversed
  for (int64_t i = 0; i < n - 2; ++i) {
    const T* D = G.voronoi.data() + i * W;
    const T* x0 = X(i, 0); const T* y0 = X(i, 1); const T* z0 = X(i, 2);
    const T* x1 = X(i + 1, 0); const T* y1 = X(i + 1, 1); const T* z1 = X(i + 1, 2);
    const T* x2 = X(i + 2, 0); const T* y2 = X(i + 2, 1); const T* z2 = X(i + 2, 2);
    const T* u0 = V(i, 0); const T* w0 = V(i, 1); const T* q0 = V(i, 2);
    const T* u1 = V(i + 1, 0); const T* w1 = V(i + 1, 1); const T* q1 = V(i + 1, 2);
    const T* u2 = V(i + 2, 0); const T* w2 = V(i + 2, 1); const T* q2 = V(i + 2, 2);
    const T* goax = A(gG, i, 0); const T* goay = A(gG, i, 1); const T* goaz = A(gG, i, 2);
    const T* gobx = A(gG, i + 1, 0); const T* goby = A(gG, i + 1, 1); const T* gobz = A(gG, i + 1, 2);
    T* px0 = A(gx, i, 0); T* py0 = A(gx, i, 1); T* pz0 = A(gx, i, 2);
    T* px1 = A(gx, i + 1, 0); T* py1 = A(gx, i + 1, 1); T* pz1 = A(gx, i + 1, 2);
    T* px2 = A(gx, i + 2, 0); T* py2 = A(gx, i + 2, 1); T* pz2 = A(gx, i + 2, 2);
    T* vx0 = A(gv, i, 0); T* vy0 = A(gv, i, 1); T* vz0 = A(gv, i, 2);
    T* vx1 = A(gv, i + 1, 0); T* vy1 = A(gv, i + 1, 1); T* vz1 = A(gv, i + 1, 2);
    T* vx2 = A(gv, i + 2, 0); T* vy2 = A(gv, i + 2, 1); T* vz2 = A(gv, i + 2, 2);
#pragma GCC ivdep
    for (int l = 0; l < W; ++l) {
      // forward
      const T rax = u1[l] - u0[l], ray = w1[l] - w0[l], raz = q1[l] - q0[l];
      const T rbx = u2[l] - u1[l], rby = w2[l] - w1[l], rbz = q2[l] - q1[l];
      const T ex = x1[l] - x0[l], ey = y1[l] - y0[l], ez = z1[l] - z0[l];
      const T fx = x2[l] - x1[l], fy = y2[l] - y1[l], fz = z2[l] - z1[l];
      const T la = std::sqrt(ex * ex + ey * ey + ez * ez);
      const T lb = std::sqrt(fx * fx + fy * fy + fz * fz);
      const T ax = ex / la, ay = ey / la, az = ez / la;
      const T bx = fx / lb, by = fy / lb, bz = fz / lb;
      const T c = ax * bx + ay * by + az * bz;
      const T pax = bx - c * ax, pay = by - c * ay, paz = bz - c * az;
      const T pbx = ax - c * bx, pby = ay - c * by, pbz = az - c * bz;
      const T one_c = T(1) + c;
      const T dE_dc = -T(4) * ei[l] / (D[l] * one_c * one_c);
      const T na2 = pax * pax + pay * pay + paz * paz;
      const T nb2 = pbx * pbx + pby * pby + pbz * pbz;
      const T tiny2 = T(TINY * TINY);
      const T ia = na2 > tiny2 ? T(1) / std::sqrt(std::max(na2, tiny2)) : T(0);
      const T ib = nb2 > tiny2 ? T(1) / std::sqrt(std::max(nb2, tiny2)) : T(0);
      const T tax = pax * ia / la, tay = pay * ia / la, taz = paz * ia / la;
      const T tbx = pbx * ib / lb, tby = pby * ib / lb, tbz = pbz * ib / lb;
      const T ds = T(2) / one_c;
      const T qr = tax * rax + tay * ray + taz * raz + tbx * rbx + tby * rby + tbz * rbz;
      const T K = eta_b[l] / D[l];
      const T scale = K * ds * ds * qr;                 // = -eta_B / D bend_rate ds, bend_rate = -ds qr
      // reverse: out_a = dE_dc pa / la + scale ta, out_b = dE_dc pb / lb + scale tb
      const T oax = goax[l], oay = goay[l], oaz = goaz[l], obx = gobx[l], oby = goby[l], obz = gobz[l];
      const T oa_pa = oax * pax + oay * pay + oaz * paz, ob_pb = obx * pbx + oby * pby + obz * pbz;
      const T g_dE = oa_pa / la + ob_pb / lb;
      T gpax = dE_dc / la * oax, gpay = dE_dc / la * oay, gpaz = dE_dc / la * oaz;
      T gpbx = dE_dc / lb * obx, gpby = dE_dc / lb * oby, gpbz = dE_dc / lb * obz;
      T gla = -dE_dc * oa_pa / (la * la), glb = -dE_dc * ob_pb / (lb * lb);
      const T gscale = oax * tax + oay * tay + oaz * taz + obx * tbx + oby * tby + obz * tbz;
      T gtax = scale * oax, gtay = scale * oay, gtaz = scale * oaz;
      T gtbx = scale * obx, gtby = scale * oby, gtbz = scale * obz;
      // scale = K ds^2 qr
      T gds = T(2) * K * ds * qr * gscale;
      const T gqr = K * ds * ds * gscale;
      // qr = ta.ra + tb.rb
      gtax += gqr * rax; gtay += gqr * ray; gtaz += gqr * raz;
      gtbx += gqr * rbx; gtby += gqr * rby; gtbz += gqr * rbz;
      const T grax = gqr * tax, gray = gqr * tay, graz = gqr * taz;
      const T grbx = gqr * tbx, grby = gqr * tby, grbz = gqr * tbz;
      // ds = 2 / (1 + c)
      T gone_c = -T(2) / (one_c * one_c) * gds;
      // ta = pa ia / la
      const T pa_gta = pax * gtax + pay * gtay + paz * gtaz, pb_gtb = pbx * gtbx + pby * gtby + pbz * gtbz;
      gpax += ia / la * gtax; gpay += ia / la * gtay; gpaz += ia / la * gtaz;
      gpbx += ib / lb * gtbx; gpby += ib / lb * gtby; gpbz += ib / lb * gtbz;
      const T gia = pa_gta / la, gib = pb_gtb / lb;
      gla -= ia * pa_gta / (la * la); glb -= ib * pb_gtb / (lb * lb);
      // ia = na2^(-1/2) where na2 > tiny2
      const T gna2 = -T(0.5) * ia * ia * ia * gia, gnb2 = -T(0.5) * ib * ib * ib * gib;
      gpax += T(2) * gna2 * pax; gpay += T(2) * gna2 * pay; gpaz += T(2) * gna2 * paz;
      gpbx += T(2) * gnb2 * pbx; gpby += T(2) * gnb2 * pby; gpbz += T(2) * gnb2 * pbz;
      // dE_dc = -4 EI / (D (1 + c)^2)
      gone_c += T(8) * ei[l] / (D[l] * one_c * one_c * one_c) * g_dE;
      T gc = gone_c;
      // pa = b - c a, pb = a - c b
      T gax = -c * gpax + gpbx, gay = -c * gpay + gpby, gaz = -c * gpaz + gpbz;
      T gbx = gpax - c * gpbx, gby = gpay - c * gpby, gbz = gpaz - c * gpbz;
      gc -= gpax * ax + gpay * ay + gpaz * az + gpbx * bx + gpby * by + gpbz * bz;
      // c = a.b
      gax += gc * bx; gay += gc * by; gaz += gc * bz;
      gbx += gc * ax; gby += gc * ay; gbz += gc * az;
      // a = e / la, la = |e| (and b likewise)
      gla -= (gax * ax + gay * ay + gaz * az) / la;
      glb -= (gbx * bx + gby * by + gbz * bz) / lb;
      const T gex = gax / la + gla * ax, gey = gay / la + gla * ay, gez = gaz / la + gla * az;
      const T gfx = gbx / lb + glb * bx, gfy = gby / lb + glb * by, gfz = gbz / lb + glb * bz;
      px0[l] -= gex; py0[l] -= gey; pz0[l] -= gez;
      px1[l] += gex - gfx; py1[l] += gey - gfy; pz1[l] += gez - gfz;
      px2[l] += gfx; py2[l] += gfy; pz2[l] += gfz;
      vx0[l] -= grax; vy0[l] -= gray; vz0[l] -= graz;
      vx1[l] += grax - grbx; vy1[l] += gray - grby; vz1[l] += graz - grbz;
      vx2[l] += grbx; vy2[l] += grby; vz2[l] += grbz;
    }
  }
}

// The gradient of a group's outputs (x, v at each lane's stop frame) w.r.t. its start state, path and hold: the
// forward run again with the state kept at every frame's start, then each frame re-run from it keeping its
// substeps' states and reversed. Memory: one group's frames, per thread.
template <typename T>
void backward_group(const Ints& in, const Reals& re, int64_t group, const int64_t* held, const T* x0, const T* v0,
                    const T* path, const T* hold, const T* phys, const int64_t* frames, const T* gx_out,
                    const T* gv_out, T* gx0, T* gv0, T* gpath, T* ghold) {
  Run<T> R(in, re, group, held, x0, v0, path, hold, phys);
  Group<T>& G = R.G;
  const int64_t n = in.n, H = in.n_held, B = in.B, S = in.substeps;
  const int64_t state = n * 3 * W;
  int64_t stop[W], last = 0;
  for (int l = 0; l < W; ++l) { stop[l] = frames[R.lane_b[l]]; last = std::max(last, stop[l]); }
  std::vector<T> cx(last * state), cv(last * state), sx(S * state), sv(S * state);
  R.start();
  for (int64_t k = 1; k <= last; ++k) {
    std::copy(G.x.begin(), G.x.end(), cx.begin() + (k - 1) * state);
    std::copy(G.v.begin(), G.v.end(), cv.begin() + (k - 1) * state);
    R.frame(k);
  }
  std::vector<T> gx(state, T(0)), gv(state, T(0)), gF(state, T(0)), gG(state, T(0));
  std::vector<T> gs(H * 3 * W), ge(H * 3 * W), gvh(H * 3 * W);
  std::vector<T> gp(in.path_frames * H * 3 * W, T(0)), gh(H * 3 * W, T(0));    // [frame][held][axis][lane]
  auto add_path = [&](int64_t k, const std::vector<T>& g) {
    T* dst = k <= R.move_frames ? gp.data() + k * H * 3 * W : gh.data();
    for (int64_t o = 0; o < H * 3 * W; ++o) dst[o] += g[o];
  };
  for (int64_t k = last; k >= 1; --k) {
    for (int l = 0; l < W; ++l) {
      if (stop[l] != k || group * W + l >= B) continue;
      const int64_t b = group * W + l;
      for (int64_t j = 0; j < n; ++j)
        for (int d = 0; d < 3; ++d) {
          gx[(j * 3 + d) * W + l] += gx_out[(b * n + j) * 3 + d];
          gv[(j * 3 + d) * W + l] += gv_out[(b * n + j) * 3 + d];
        }
    }
    std::copy(cx.begin() + (k - 1) * state, cx.begin() + k * state, G.x.begin());
    std::copy(cv.begin() + (k - 1) * state, cv.begin() + k * state, G.v.begin());
    R.begin_frame(k);
    for (int64_t s = 1; s <= S; ++s) {
      std::copy(G.x.begin(), G.x.end(), sx.begin() + (s - 1) * state);
      std::copy(G.v.begin(), G.v.end(), sv.begin() + (s - 1) * state);
      if (s < S) substep(G, held, H, R.h, R.alpha(s), R.vh.data());
    }
    std::fill(gs.begin(), gs.end(), T(0)); std::fill(ge.begin(), ge.end(), T(0));
    std::fill(gvh.begin(), gvh.end(), T(0));
    for (int64_t s = S; s >= 1; --s) {
      std::copy(sx.begin() + (s - 1) * state, sx.begin() + s * state, G.x.begin());
      std::copy(sv.begin() + (s - 1) * state, sv.begin() + s * state, G.v.begin());
      substep_backward(G, held, H, R.h, R.alpha(s), gx.data(), gv.data(), gs.data(), ge.data(), gvh.data(),
                       gF.data(), gG.data());
    }
    // begin_frame: x_held = start, v_held = vh = (end - start) / dt
    for (int64_t q = 0; q < H; ++q)
      for (int d = 0; d < 3; ++d)
        for (int l = 0; l < W; ++l) {
          const int64_t o = (q * 3 + d) * W + l, a = (held[q] * 3 + d) * W + l;
          gs[o] += gx[a]; gvh[o] += gv[a]; gx[a] = T(0); gv[a] = T(0);
          ge[o] += gvh[o] / R.dt; gs[o] -= gvh[o] / R.dt;
        }
    if (k <= R.move_frames) { add_path(k - 1, gs); add_path(k, ge); }
    else { add_path(k, gs); add_path(k, ge); }
  }
  // frame 0 (start): x_held = path[0], v_held = (path[1] - path[0]) / dt (0 without a move)
  for (int64_t q = 0; q < H; ++q)
    for (int d = 0; d < 3; ++d)
      for (int l = 0; l < W; ++l) {
        const int64_t o = (q * 3 + d) * W + l, a = (held[q] * 3 + d) * W + l;
        gp[o] += gx[a];
        if (in.path_frames > 1) { gp[H * 3 * W + o] += gv[a] / R.dt; gp[o] -= gv[a] / R.dt; }
        gx[a] = T(0); gv[a] = T(0);
      }
  for (int l = 0; l < W; ++l) {
    const int64_t b = group * W + l;
    if (b >= B) continue;
    for (int64_t j = 0; j < n; ++j)
      for (int d = 0; d < 3; ++d) {
        gx0[(b * n + j) * 3 + d] = gx[(j * 3 + d) * W + l];
        gv0[(b * n + j) * 3 + d] = gv[(j * 3 + d) * W + l];
      }
    for (int64_t q = 0; q < H; ++q)
      for (int d = 0; d < 3; ++d) {
        ghold[(b * H + q) * 3 + d] = gh[(q * 3 + d) * W + l];
        for (int64_t k = 0; k < in.path_frames; ++k)
          gpath[((k * B + b) * H + q) * 3 + d] = gp[((k * H + q) * 3 + d) * W + l];
      }
  }
}

template <typename T>
void move(const double* fp, const int64_t* ip, const int64_t* held, const T* x0, const T* v0, const T* path,
          const T* hold, const T* phys, T* x_out, T* v_out, uint8_t* settled, int64_t* frames, int64_t* diverged) {
  const Ints in{ip[0], ip[1], ip[2], ip[3], ip[4], ip[5], ip[6], ip[7]};
  const Reals re{fp[0], fp[1], fp[2]};
  const int64_t groups = (in.B + W - 1) / W;
  parallel_for(groups, in.threads, [&](int64_t g) {
    run_group<T>(in, re, g, held, x0, v0, path, hold, phys, x_out, v_out, settled, frames, diverged);
  });
}

template <typename T>
void backward(const double* fp, const int64_t* ip, const int64_t* held, const T* x0, const T* v0, const T* path,
              const T* hold, const T* phys, const int64_t* frames, const T* gx_out, const T* gv_out, T* gx0, T* gv0,
              T* gpath, T* ghold) {
  const Ints in{ip[0], ip[1], ip[2], ip[3], ip[4], ip[5], ip[6], ip[7]};
  const Reals re{fp[0], fp[1], fp[2]};
  const int64_t groups = (in.B + W - 1) / W;
  parallel_for(groups, in.threads, [&](int64_t g) {
    backward_group<T>(in, re, g, held, x0, v0, path, hold, phys, frames, gx_out, gv_out, gx0, gv0, gpath, ghold);
  });
}

}  // namespace

extern "C" {
int64_t chain3d_lanes() { return W; }
void chain3d_move_f32(const double* fp, const int64_t* ip, const int64_t* held, const float* x0, const float* v0,
                      const float* path, const float* hold, const float* phys, float* x_out, float* v_out,
                      uint8_t* settled, int64_t* frames, int64_t* diverged) {
  move<float>(fp, ip, held, x0, v0, path, hold, phys, x_out, v_out, settled, frames, diverged);
}
void chain3d_move_f64(const double* fp, const int64_t* ip, const int64_t* held, const double* x0, const double* v0,
                      const double* path, const double* hold, const double* phys, double* x_out, double* v_out,
                      uint8_t* settled, int64_t* frames, int64_t* diverged) {
  move<double>(fp, ip, held, x0, v0, path, hold, phys, x_out, v_out, settled, frames, diverged);
}
void chain3d_backward_f32(const double* fp, const int64_t* ip, const int64_t* held, const float* x0, const float* v0,
                          const float* path, const float* hold, const float* phys, const int64_t* frames,
                          const float* gx_out, const float* gv_out, float* gx0, float* gv0, float* gpath,
                          float* ghold) {
  backward<float>(fp, ip, held, x0, v0, path, hold, phys, frames, gx_out, gv_out, gx0, gv0, gpath, ghold);
}
void chain3d_backward_f64(const double* fp, const int64_t* ip, const int64_t* held, const double* x0,
                          const double* v0, const double* path, const double* hold, const double* phys,
                          const int64_t* frames, const double* gx_out, const double* gv_out, double* gx0,
                          double* gv0, double* gpath, double* ghold) {
  backward<double>(fp, ip, held, x0, v0, path, hold, phys, frames, gx_out, gv_out, gx0, gv0, gpath, ghold);
}
}
