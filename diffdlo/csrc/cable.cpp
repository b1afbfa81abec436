// Fused CPU kernel of diffdlo's move (kinematic grasp -> drag -> release -> settle) and free evolution, with a
// hand-written adjoint. Plain C++ with a C ABI (called through ctypes on tensor data pointers); the pure-torch
// path in diffdlo/simulator.py is the reference and the test oracle, and this file mirrors it step by step:
//   forces   : diffdlo/forces.py internal_forces (dE/de per link, scattered to nodes)
//   substep  : diffdlo/integrate.py semi_implicit_step (implicit damping)
//   grasp    : diffdlo/control.py reference (straight path at constant speed; node overwritten while dragging)
//   settle   : Simulator.move (speed checked every check_every substeps after release, capped)
// Each rope is independent, so ropes run in parallel (a few std::threads taking ropes from an atomic counter;
// not OpenMP, whose spinning idle threads would fight PyTorch's own OpenMP runtime for the cores) and each rope
// stops at its own substep.
// The backward recomputes one rope's trajectory inside its own thread, then runs the adjoint with an analytic
// Hessian-vector product of the energy: memory is O(threads x one trajectory), whatever B or the move count.
#include <algorithm>
#include <cmath>
#include <cstdint>
#include <memory>
#include <vector>
#include <atomic>
#include <thread>

namespace {

// Run body(b) for b in [0, B) on up to `threads` threads (inline when one suffices).
template <typename F>
void parallel_for(int64_t B, int64_t threads, F body) {
  const int64_t workers = std::max<int64_t>(1, std::min(threads, B));
  if (workers == 1) {
    for (int64_t b = 0; b < B; ++b) body(b);
    return;
  }
  std::atomic<int64_t> next{0};
  auto work = [&]() {
    for (int64_t b = next.fetch_add(1); b < B; b = next.fetch_add(1)) body(b);
  };
  std::vector<std::thread> pool;
  for (int64_t t = 1; t < workers; ++t) pool.emplace_back(work);
  work();
  for (auto& t : pool) t.join();
}

struct Scalars {      // fp[] from Python, in this order
  double l0, ks, kb, h, inv_m, damp, vmax, threshold, radius;
};
struct Ints {         // ip[] from Python, in this order
  int64_t B, n, max_drag, check_every, max_settle, fixed_steps, threads;
};

template <typename T>
struct Work {         // per-rope scratch
  std::vector<T> e, len2, beta, G, F, we, dbeta;
  explicit Work(int64_t n) : e(2 * (n - 1)), len2(n - 1), beta(n - 2), G(2 * (n - 1)), F(2 * n),
                             we(2 * (n - 1)), dbeta(n - 2) {}
};

// Link vectors, squared lengths, signed turning angles.
template <typename T>
inline void geometry(int64_t n, const T* x, Work<T>& w) {
  const int64_t L = n - 1;
  for (int64_t k = 0; k < L; ++k) {
    w.e[2 * k] = x[2 * k + 2] - x[2 * k];
    w.e[2 * k + 1] = x[2 * k + 3] - x[2 * k + 1];
    w.len2[k] = w.e[2 * k] * w.e[2 * k] + w.e[2 * k + 1] * w.e[2 * k + 1];
  }
  for (int64_t j = 0; j < L - 1; ++j) {
    const T ax = w.e[2 * j], ay = w.e[2 * j + 1], bx = w.e[2 * j + 2], by = w.e[2 * j + 3];
    w.beta[j] = std::atan2(ax * by - ay * bx, ax * bx + ay * by);
  }
}

// Internal forces F = -dE/dx into w.F.
template <typename T>
inline void forces(const Scalars& s, int64_t n, const T* x, Work<T>& w) {
  geometry(n, x, w);
  const int64_t L = n - 1;
  const T l0 = T(s.l0), ks = T(s.ks), kb = T(s.kb);
  for (int64_t k = 0; k < L; ++k) {
    const T len = std::sqrt(w.len2[k]);
    const T a = ks * (T(1) - l0 / len);
    const T bs = k > 0 ? w.beta[k - 1] : T(0);
    const T be = k < L - 1 ? w.beta[k] : T(0);
    const T b = kb * (bs - be) / w.len2[k];
    const T ex = w.e[2 * k], ey = w.e[2 * k + 1];
    w.G[2 * k] = a * ex - b * ey;       // perp(e) = (-ey, ex)
    w.G[2 * k + 1] = a * ey + b * ex;
  }
  for (int64_t j = 0; j < n; ++j) {
    for (int c = 0; c < 2; ++c) {
      const T out = j < L ? w.G[2 * j + c] : T(0);
      const T in = j > 0 ? w.G[2 * (j - 1) + c] : T(0);
      w.F[2 * j + c] = out - in;
    }
  }
}

// Hessian-vector product H u of the energy at x, into out (n x 2).
template <typename T>
inline void hvp(const Scalars& s, int64_t n, const T* x, const T* u, T* out, Work<T>& w,
                const T* beta = nullptr) {
  const int64_t L = n - 1;
  if (beta) {            // turning angles stored by the forward recomputation: skip atan2
    for (int64_t k = 0; k < L; ++k) {
      w.e[2 * k] = x[2 * k + 2] - x[2 * k];
      w.e[2 * k + 1] = x[2 * k + 3] - x[2 * k + 1];
      w.len2[k] = w.e[2 * k] * w.e[2 * k] + w.e[2 * k + 1] * w.e[2 * k + 1];
    }
    std::copy(beta, beta + (n - 2), w.beta.begin());
  } else {
    geometry(n, x, w);
  }
  const T l0 = T(s.l0), ks = T(s.ks), kb = T(s.kb);
  for (int64_t k = 0; k < L; ++k) {
    w.we[2 * k] = u[2 * k + 2] - u[2 * k];
    w.we[2 * k + 1] = u[2 * k + 3] - u[2 * k + 1];
  }
  // d beta_j = q(e_{j+1}) . we_{j+1} - q(e_j) . we_j with q(e) = perp(e) / |e|^2
  auto qdot = [&](int64_t k) {
    return (-w.e[2 * k + 1] * w.we[2 * k] + w.e[2 * k] * w.we[2 * k + 1]) / w.len2[k];
  };
  for (int64_t j = 0; j < L - 1; ++j) w.dbeta[j] = qdot(j + 1) - qdot(j);
  for (int64_t k = 0; k < L; ++k) {
    const T ex = w.e[2 * k], ey = w.e[2 * k + 1], ux = w.we[2 * k], uy = w.we[2 * k + 1];
    const T l2 = w.len2[k], len = std::sqrt(l2);
    const T edotu = ex * ux + ey * uy;
    const T a = ks * (T(1) - l0 / len), c = ks * l0 / (len * l2);
    const T bs = k > 0 ? w.beta[k - 1] : T(0);
    const T be = k < L - 1 ? w.beta[k] : T(0);
    const T dbs = k > 0 ? w.dbeta[k - 1] : T(0);
    const T dbe = k < L - 1 ? w.dbeta[k] : T(0);
    // dG = ks[(1 - l0/l) u + l0/l^3 (e.u) e] + kb[(dbs - dbe) q + (bs - be) dq],
    // q = perp(e)/l^2, dq = perp(u)/l^2 - 2 (e.u) perp(e)/l^4
    const T qx = -ey / l2, qy = ex / l2;
    const T dqx = -uy / l2 + T(2) * edotu * ey / (l2 * l2);
    const T dqy = ux / l2 - T(2) * edotu * ex / (l2 * l2);
    w.G[2 * k] = a * ux + c * edotu * ex + kb * ((dbs - dbe) * qx + (bs - be) * dqx);
    w.G[2 * k + 1] = a * uy + c * edotu * ey + kb * ((dbs - dbe) * qy + (bs - be) * dqy);
  }
  for (int64_t j = 0; j < n; ++j) {
    for (int c = 0; c < 2; ++c) {
      const T in = j > 0 ? w.G[2 * (j - 1) + c] : T(0);
      const T outg = j < L ? w.G[2 * j + c] : T(0);
      out[2 * j + c] = in - outg;     // (H u)_j = dG_{j-1} - dG_j
    }
  }
}

template <typename T>
inline void substep(const Scalars& s, int64_t n, T* x, T* v, Work<T>& w) {
  forces(s, n, x, w);
  const T h = T(s.h), hm = T(s.h * s.inv_m), damp = T(s.damp);
  for (int64_t i = 0; i < 2 * n; ++i) {
    v[i] = (v[i] + hm * w.F[i]) * damp;
    x[i] += h * v[i];
  }
}

// Reference position/velocity of the grasped node at drag substep k (control.reference).
template <typename T>
inline void reference(const T* start, const T* d, T speed, int64_t k, T h, T* ref, T* refv, T* raw_out) {
  const T dist = std::sqrt(d[0] * d[0] + d[1] * d[1]);
  const T safe = std::max(dist, T(1e-12));
  const T raw = T(k) * h * speed / safe;
  const T frac = std::min(raw, T(1));
  const T moving = raw <= T(1) ? T(1) : T(0);
  for (int c = 0; c < 2; ++c) {
    ref[c] = start[c] + frac * d[c];
    refv[c] = moving * speed / safe * d[c];
  }
  *raw_out = raw;
}

// Run one rope. Returns the number of substeps done; if traj != nullptr stores x_0..x_K (n*2 each).
template <typename T>
int64_t run_rope(const Scalars& s, const Ints& in, T* x, T* v, int64_t g, const T* d, T speed, int64_t n_grasp,
                 T* traj, T* betas, int64_t* settled, int64_t* diverged, Work<T>& w) {
  const int64_t n = in.n;
  const T h = T(s.h);
  T start[2] = {x[2 * g], x[2 * g + 1]};
  T ref[2], refv[2], raw;
  *settled = 0;
  *diverged = 0;
  if (traj) std::copy(x, x + 2 * n, traj);
  auto bad = [&]() {
    for (int64_t i = 0; i < 2 * n; ++i)
      if (!std::isfinite(x[i]) || std::abs(x[i]) > T(s.radius)) return true;
    return false;
  };
  for (int64_t k = 1;; ++k) {
    substep(s, n, x, v, w);
    if (betas) std::copy(w.beta.begin(), w.beta.end(), betas + (n - 2) * (k - 1));   // beta(x_{k-1})
    if (k <= n_grasp) {
      reference(start, d, speed, k, h, ref, refv, &raw);
      x[2 * g] = ref[0];
      x[2 * g + 1] = ref[1];
      v[2 * g] = refv[0];
      v[2 * g + 1] = refv[1];
    }
    if (traj) std::copy(x, x + 2 * n, traj + 2 * n * k);
    if (in.fixed_steps >= 0) {
      if (k >= in.fixed_steps) {
        *diverged = bad();
        return k;
      }
      continue;
    }
    const int64_t since = k - n_grasp;
    const bool check = since > 0 && since % in.check_every == 0;
    const bool capped = since >= in.max_settle;
    if (check || capped) {
      if (bad()) {
        *diverged = 1;
        return k;
      }
      if (check) {
        T vmax2 = 0;
        for (int64_t j = 0; j < n; ++j) vmax2 = std::max(vmax2, v[2 * j] * v[2 * j] + v[2 * j + 1] * v[2 * j + 1]);
        if (std::sqrt(vmax2) < T(s.threshold)) {
          *settled = 1;
          return k;
        }
      }
      if (capped) return k;
    }
  }
}

template <typename T>
void forward(const double* fp, const int64_t* ip, const T* pos, const T* vel, const int64_t* node, const T* delta,
             const T* speed, const int64_t* n_grasp, T* out_pos, T* out_vel, int64_t* out_steps,
             int64_t* out_settled, int64_t* out_diverged) {
  const Scalars s{fp[0], fp[1], fp[2], fp[3], fp[4], fp[5], fp[6], fp[7], fp[8]};
  const Ints in{ip[0], ip[1], ip[2], ip[3], ip[4], ip[5], ip[6]};
  const int64_t n = in.n;
  parallel_for(in.B, in.threads, [&](int64_t b) {
    Work<T> w(n);
    T* x = out_pos + 2 * n * b;
    T* v = out_vel + 2 * n * b;
    std::copy(pos + 2 * n * b, pos + 2 * n * (b + 1), x);
    if (vel) std::copy(vel + 2 * n * b, vel + 2 * n * (b + 1), v);
    else std::fill(v, v + 2 * n, T(0));
    out_steps[b] = run_rope(s, in, x, v, node[b], delta + 2 * b, speed[b], n_grasp[b], static_cast<T*>(nullptr),
                            static_cast<T*>(nullptr), out_settled + b, out_diverged + b, w);
  });
}

template <typename T>
void backward(const double* fp, const int64_t* ip, const T* pos, const T* vel, const int64_t* node, const T* delta,
              const T* speed, const int64_t* n_grasp, const T* grad_out_pos, const T* grad_out_vel, T* grad_pos,
              T* grad_vel, T* grad_delta) {
  const Scalars s{fp[0], fp[1], fp[2], fp[3], fp[4], fp[5], fp[6], fp[7], fp[8]};
  const Ints in{ip[0], ip[1], ip[2], ip[3], ip[4], ip[5], ip[6]};
  const int64_t n = in.n;
  const int64_t max_steps = in.fixed_steps >= 0 ? in.fixed_steps : in.max_drag + in.max_settle + 1;
  parallel_for(in.B, in.threads, [&](int64_t b) {
    Work<T> w(n);
    // uninitialised: every slot read is written by the recomputation first
    std::unique_ptr<T[]> traj(new T[2 * n * (max_steps + 2)]), betas(new T[(n - 2) * (max_steps + 1)]);
    std::vector<T> x(2 * n), v(2 * n), hu(2 * n);
    std::copy(pos + 2 * n * b, pos + 2 * n * (b + 1), x.begin());
    if (vel) std::copy(vel + 2 * n * b, vel + 2 * n * (b + 1), v.begin());
    else std::fill(v.begin(), v.end(), T(0));
    const int64_t g = node[b];
    const T* d = delta + 2 * b;
    const T sp = speed[b];
    int64_t settled, diverged;
    const int64_t K = run_rope(s, in, x.data(), v.data(), g, d, sp, n_grasp[b], traj.get(), betas.get(), &settled,
                               &diverged, w);

    T* gx = grad_pos + 2 * n * b;
    T* gv = grad_vel + 2 * n * b;
    std::copy(grad_out_pos + 2 * n * b, grad_out_pos + 2 * n * (b + 1), gx);
    if (grad_out_vel) std::copy(grad_out_vel + 2 * n * b, grad_out_vel + 2 * n * (b + 1), gv);
    else std::fill(gv, gv + 2 * n, T(0));
    T gd[2] = {0, 0}, gstart[2] = {0, 0};
    const T h = T(s.h), vmax = T(s.vmax);
    const T dist = std::sqrt(d[0] * d[0] + d[1] * d[1]);
    const T safe = std::max(dist, T(1e-12));
    const T ux = d[0] / safe, uy = d[1] / safe;
    const bool fast = sp > vmax;   // speed = dist / (max_drag h): the path takes exactly max_drag substeps
    const T md = T(in.max_drag);
    const T coef = h * s.inv_m * s.damp;
    for (int64_t k = K; k >= 1; --k) {
      if (k <= n_grasp[b]) {
        // x_k[g] = start + frac_k d,  v_k[g] = moving_k * speed / |d| * d
        const T raw = T(k) * h * sp / safe;
        const T a0 = gx[2 * g], a1 = gx[2 * g + 1], c0 = gv[2 * g], c1 = gv[2 * g + 1];
        gstart[0] += a0;
        gstart[1] += a1;
        if (raw > T(1)) {                 // on the goal: d(ref)/dd = I
          gd[0] += a0;
          gd[1] += a1;
        } else if (fast) {                // frac = k / max_drag, refv = d / (max_drag h)
          gd[0] += T(k) / md * a0 + c0 / (md * h);
          gd[1] += T(k) / md * a1 + c1 / (md * h);
        } else {                          // ref = start + k h vmax u, refv = vmax u; du/dd = (I - u u^T)/|d|
          const T pa = (a0 * ux + a1 * uy), pc = (c0 * ux + c1 * uy);
          const T fa = T(k) * h * vmax / safe, fc = vmax / safe;
          gd[0] += fa * (a0 - pa * ux) + fc * (c0 - pc * ux);
          gd[1] += fa * (a1 - pa * uy) + fc * (c1 - pc * uy);
        }
        gx[2 * g] = gx[2 * g + 1] = gv[2 * g] = gv[2 * g + 1] = T(0);
      }
      // x_k = x_{k-1} + h v_k, v_k = damp (v_{k-1} + h/m F(x_{k-1})), F = -grad E
      for (int64_t i = 0; i < 2 * n; ++i) v[i] = gv[i] + h * gx[i];      // v reused as u
      hvp(s, n, traj.get() + 2 * n * (k - 1), v.data(), hu.data(), w, betas.get() + (n - 2) * (k - 1));
      for (int64_t i = 0; i < 2 * n; ++i) {
        gx[i] -= coef * hu[i];
        gv[i] = T(s.damp) * v[i];
      }
    }
    if (n_grasp[b] > 0) {
      gx[2 * g] += gstart[0];
      gx[2 * g + 1] += gstart[1];
    }
    grad_delta[2 * b] = gd[0];
    grad_delta[2 * b + 1] = gd[1];
  });
}

}  // namespace

extern "C" {
#define DIFFDLO_EXPORT(T, SUFFIX)                                                                                  \
  void diffdlo_forward_##SUFFIX(const double* fp, const int64_t* ip, const T* pos, const T* vel,                   \
                                const int64_t* node, const T* delta, const T* speed, const int64_t* n_grasp,       \
                                T* out_pos, T* out_vel, int64_t* steps, int64_t* settled, int64_t* diverged) {     \
    forward<T>(fp, ip, pos, vel, node, delta, speed, n_grasp, out_pos, out_vel, steps, settled, diverged);         \
  }                                                                                                                \
  void diffdlo_backward_##SUFFIX(const double* fp, const int64_t* ip, const T* pos, const T* vel,                  \
                                 const int64_t* node, const T* delta, const T* speed, const int64_t* n_grasp,      \
                                 const T* gpos_out, const T* gvel_out, T* gpos, T* gvel, T* gdelta) {              \
    backward<T>(fp, ip, pos, vel, node, delta, speed, n_grasp, gpos_out, gvel_out, gpos, gvel, gdelta);            \
  }                                                                                                                \
  void diffdlo_hvp_##SUFFIX(const double* fp, int64_t n, const T* x, const T* u, T* out) {                         \
    const Scalars s{fp[0], fp[1], fp[2], fp[3], fp[4], fp[5], fp[6], fp[7], fp[8]};                                \
    Work<T> w(n);                                                                                                  \
    hvp(s, n, x, u, out, w);                                                                                       \
  }
DIFFDLO_EXPORT(float, f32)
DIFFDLO_EXPORT(double, f64)
}
