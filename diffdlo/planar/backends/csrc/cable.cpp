// Fused CPU kernel of diffdlo's move (kinematic grasp -> drag -> release -> settle) and free evolution, with a
// hand-written adjoint. Plain C++ with a C ABI (called through ctypes on tensor data pointers); the pure-torch
// path in diffdlo/planar/simulator.py is the reference and the test oracle, and this file mirrors it step by step:
//   forces   : diffdlo/planar/forces.py internal_forces (dE/de per link, scattered to nodes)
//   substep  : diffdlo/planar/integrate.py semi_implicit_step (implicit damping)
//   grasp    : diffdlo/planar/control.py reference (straight path at constant speed; node overwritten while dragging)
//   settle   : Simulator.move (speed checked every check_every substeps after release, capped)
// Each rope is independent, so ropes run in parallel (a few std::threads taking ropes from an atomic counter;
// not OpenMP, whose spinning idle threads would fight PyTorch's own OpenMP runtime for the cores) and each rope
// stops at its own substep.
// The backward recomputes one rope's trajectory inside its own thread, then runs the adjoint with an analytic
// Hessian-vector product of the energy: memory is O(threads x one trajectory), whatever B or the move count.
// Optional per-rope physics (diffdlo/planar/physics.py): phys[] holds k_s, k_b, 1/node_mass and the damping factor
// 1/(1 + h k_d / m) of each rope (null: the scalars of fp[] for every rope); the adjoint then also returns the
// gradients w.r.t. those four numbers (the chain rule to k_d and mass is left to autograd in diffdlo/kernel.py).
// Optional frames: the positions at substeps 0, E, 2E, ... (E = record_every) of each rope, up to its own stop,
// into frames[b][j] (frame_cap slots per rope); the adjoint injects their incoming gradients at those substeps.
// Optional pegs and pin (diffdlo/planar/contact.py, Simulator._move_eager): pegs[b][j] = (x, y, R) of K fixed posts per
// rope add the contact forces of every link on the table to the internal forces (the two links at the grasped node
// are lifted during the drag), and its adjoint adds the contact energy's Hessian to the Hessian-vector product;
// pin[b] (-1: none) is a second node held at its start position with velocity 0 while the rope is dragged, and
// released with the grasped node (blended by the same share phi on the last drag substep). K = 0 and no pin run
// exactly the code without them.
#include <algorithm>
#include <cmath>
#include <limits>
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

struct Scalars {      // fp[] from Python, in this order (rr, kc, cw: rope radius, contact stiffness and width)
  double l0, ks, kb, h, inv_m, damp, vmax, threshold, radius, rr, kc, cw;
};
struct Ints {         // ip[] from Python, in this order
  int64_t B, n, max_drag, check_every, max_settle, fixed_steps, threads, use_groups, record_every, frame_cap;
};

// The scalars of rope b: fp[]'s, with the per-rope physics in place of k_s, k_b, 1/m, damp where given.
inline Scalars rope_scalars(const Scalars& s, const double* phys, int64_t b) {
  Scalars r = s;
  if (phys) {
    r.ks = phys[4 * b];
    r.kb = phys[4 * b + 1];
    r.inv_m = phys[4 * b + 2];
    r.damp = phys[4 * b + 3];
  }
  return r;
}

// The release within the drag's last substep (control.last_substep_fraction): the share phi of that substep the
// path still fills, and d phi / d d (nonzero only at max_speed, where phi = |d| / (vmax h) - (n_grasp - 1)).
// phi = 1 (a whole number of substeps, a zero drag, free evolution) leaves the move as it was.
template <typename T>
inline T last_share(const T* d, T speed, int64_t n_grasp, T h, T vmax, T* dphi) {
  dphi[0] = dphi[1] = T(0);
  if (n_grasp <= 0) return T(1);
  const T len = std::sqrt(d[0] * d[0] + d[1] * d[1]);
  const T raw = len / (speed * h) - T(n_grasp - 1);
  if (!(raw < T(1))) return T(1);
  if (!(raw > T(0))) return T(0);
  if (!(speed > vmax) && len > T(0)) {
    dphi[0] = d[0] / (len * speed * h);
    dphi[1] = d[1] / (len * speed * h);
  }
  return raw;
}

// A candidate (link, peg) pair of the contact loops (see PegList below); due: in a lane group's forward run
// (group_contact_forces), the travel of its lane at which it must next be evaluated.
struct PegPair {
  int32_t k, j;
  double due = -1e300;
};

// The candidate pairs of one rope for the contact loops (see peg_list_update): built at xref.
template <typename T>
struct PegList {
  std::vector<PegPair> pairs;
  std::vector<T> xref, scratch;
  bool built = false;
};

template <typename T>
struct Work {         // per-rope scratch
  std::vector<T> e, len2, beta, G, F, we, dbeta;
  // the release (see last_share): phi, d phi / d d, the grasped node's free (x, y, vx, vy) on the last drag
  // substep, and for a rope stopped by the settle cap its state before (prev) and after (cap) the last substep
  T phi = T(1), dphi[2] = {T(0), T(0)}, free[4] = {T(0), T(0), T(0), T(0)};
  T pfree[4] = {T(0), T(0), T(0), T(0)};     // the pinned node's free (x, y, vx, vy) on the last drag substep
  bool lerped = false;
  std::vector<T> xprev, vprev, xcap, vcap;
  PegList<T> pegs;     // the contact's candidate pairs, where the rope has pegs
  explicit Work(int64_t n) : e(2 * (n - 1)), len2(n - 1), beta(n - 2), G(2 * (n - 1)), F(2 * n),
                             we(2 * (n - 1)), dbeta(n - 2), xprev(2 * n), vprev(2 * n), xcap(2 * n), vcap(2 * n) {}
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
// If dots != nullptr, also dots[0] = u . F_s(x), dots[1] = u . F_b(x), with F = k_s F_s + k_b F_b the forces:
// F = -dE/dx and u . F = -sum_links dE/de_k . (u_{k+1} - u_k).
template <typename T>
inline void hvp(const Scalars& s, int64_t n, const T* x, const T* u, T* out, Work<T>& w,
                const T* beta = nullptr, T* dots = nullptr) {
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
  if (dots) {
    T ds = 0, db = 0;
    for (int64_t k = 0; k < L; ++k) {
      const T ex = w.e[2 * k], ey = w.e[2 * k + 1], ux = w.we[2 * k], uy = w.we[2 * k + 1];
      const T l2 = w.len2[k];
      const T bs = k > 0 ? w.beta[k - 1] : T(0);
      const T be = k < L - 1 ? w.beta[k] : T(0);
      ds -= (T(1) - l0 / std::sqrt(l2)) * (ex * ux + ey * uy);
      db -= (bs - be) / l2 * (-ey * ux + ex * uy);
    }
    dots[0] = ds;
    dots[1] = db;
  }
  for (int64_t j = 0; j < n; ++j) {
    for (int c = 0; c < 2; ++c) {
      const T in = j > 0 ? w.G[2 * (j - 1) + c] : T(0);
      const T outg = j < L ? w.G[2 * j + c] : T(0);
      out[2 * j + c] = in - outg;     // (H u)_j = dG_{j-1} - dG_j
    }
  }
}

// ------------------------------------------------------------------------------------------------------------
// Contact with pegs (diffdlo/planar/contact.py). Link k (a = x_k, b = x_{k+1}, e = b - a) meets peg (c, R) at its point
// q = a + t e closest to c, t = clamp(s, 0, 1), s = (c - a).e / e.e, overlapping it by z = R + r - d, d = |q - c|;
// the energy k_c H(z) (H the smoothed half square of width w) pushes a by k_c H'(z) (1 - t) n and b by
// k_c H'(z) t n, n = (q - c) / d. The links lift - 1 and lift (at the grasped node during the drag; lift = -1:
// none) are off the table.
// The loops visit only the candidate pairs of a PegList: those whose link came within R + r + skin of the peg's
// centre at the state xref the list was built at. While every node stays within skin / 2 of xref no point of a
// link moves farther, so no other pair can touch; the list is rebuilt once a node may have moved farther (a Verlet
// list). The result is that of visiting every pair. A candidate is tested first without division nor root
// (peg_near); the lane groups' forward run also skips a candidate until its lane has travelled its clearance
// (group_contact_forces).
// Accessors take a stride S: 1 for a rope's own (n, 2) array, W for one lane of a group's layout (x + lane).

// Whether link (a, b) may come within reach of the peg's centre c: its squared distance from c (the cross
// product's square over e.e where the closest point is inside the link, else the end node's) against reach^2, with
// neither division nor root. reach2 is inflated by a relative 1e-4 so that rounding never turns away a pair that
// touches; a pair let through in error computes z <= 0 and adds nothing.
template <typename T>
inline bool peg_near(T ax, T ay, T bx, T by, T cx, T cy, T reach2) {
  const T ex = bx - ax, ey = by - ay, cax = cx - ax, cay = cy - ay;
  const T num = cax * ex + cay * ey, ee = ex * ex + ey * ey, cross = cax * ey - cay * ex;
  const T cbx = cx - bx, cby = cy - by;
  const T lhs = num <= T(0) ? cax * cax + cay * cay : num >= ee ? cbx * cbx + cby * cby : cross * cross;
  const T rhs = num <= T(0) || num >= ee ? reach2 : reach2 * ee;
  return lhs < rhs * T(1.0001);
}

// The closest point of link (a, e) to peg centre c: s, t, r = q - c, d = |r| (at least 1e-12) and z = reach - d.
template <typename T>
inline void peg_closest(T ax, T ay, T ex, T ey, T cx, T cy, T reach, T& sv, T& t, T& rx, T& ry, T& d, T& z) {
  sv = ((cx - ax) * ex + (cy - ay) * ey) / (ex * ex + ey * ey);
  t = std::min(std::max(sv, T(0)), T(1));
  rx = ax + t * ex - cx;
  ry = ay + t * ey - cy;
  d = std::sqrt(std::max(rx * rx + ry * ry, T(1e-24)));
  z = reach - d;
}

// The margin of the candidate lists [m]: wider lists hold more pairs, narrower ones are rebuilt more often. Half a
// link suits the drags (0.1 mm per substep at max_speed: a list lasts ~60 substeps of a drag), measured with
// benchmarks/speed/sim_speed.py --pegs.
template <typename T>
inline T peg_skin(const Scalars& s) { return T(0.5 * s.l0); }

// Rebuilds pairs (link k, peg j), ordered by j then k, of the rope at x (stride S): the candidates, whose link
// comes within R + r + skin of the peg's centre. scratch: 3 n values (the test runs across the links).
template <int S, typename T>
inline void peg_pairs(int64_t n, const T* x, const T* pegs, int64_t K, T rr, T skin, T* __restrict scratch,
                      std::vector<PegPair>& pairs) {
  pairs.clear();
  T* __restrict xs = scratch;
  T* __restrict ys = scratch + n;
  T* __restrict near = scratch + 2 * n;
  for (int64_t i = 0; i < n; ++i) {
    xs[i] = x[(2 * i) * S];
    ys[i] = x[(2 * i + 1) * S];
  }
  for (int64_t j = 0; j < K; ++j) {
    const T cx = pegs[3 * j], cy = pegs[3 * j + 1], reach = pegs[3 * j + 2] + rr + skin, reach2 = reach * reach;
    for (int64_t k = 0; k < n - 1; ++k)
      near[k] = peg_near(xs[k], ys[k], xs[k + 1], ys[k + 1], cx, cy, reach2) ? T(1) : T(0);
    for (int64_t k = 0; k < n - 1; ++k)
      if (near[k] != T(0)) pairs.push_back(PegPair{int32_t(k), int32_t(j)});
  }
}

// The list of one rope (per-rope path), valid at x afterwards.
template <typename T>
inline void peg_list_update(const Scalars& s, int64_t n, const T* x, const T* pegs, int64_t K, PegList<T>& list) {
  const T skin = peg_skin<T>(s);
  if (list.built) {
    T m = 0;
    for (int64_t i = 0; i < 2 * n; i += 2) {
      const T dx = x[i] - list.xref[i], dy = x[i + 1] - list.xref[i + 1];
      m = std::max(m, dx * dx + dy * dy);
    }
    if (m <= T(0.45 * 0.45) * skin * skin) return;      // within 0.45 skin: a margin for rounding
  }
  list.scratch.resize(3 * n);
  peg_pairs<1>(n, x, pegs, K, T(s.rr), skin, list.scratch.data(), list.pairs);
  list.xref.assign(x, x + 2 * n);
  list.built = true;
}

// The contact force of link k (x, F stride S) and one peg, added into F; returns the clearance d - (R + r)
// (<= 0 in contact).
template <int S, typename T>
inline T peg_force(T rr, T kc, T cw, const T* x, const T* peg, int64_t k, T* F) {
  const T ax = x[(2 * k) * S], ay = x[(2 * k + 1) * S], bx = x[(2 * k + 2) * S], by = x[(2 * k + 3) * S];
  const T reach = peg[2] + rr;
  T sv, t, rx, ry, d, z;
  peg_closest(ax, ay, bx - ax, by - ay, peg[0], peg[1], reach, sv, t, rx, ry, d, z);
  // without a branch (whether a due pair touches is hard to predict): a pair clear of the peg adds zeros
  const T zp = std::max(z, T(0));
  const T h1 = zp < cw ? zp * zp / (T(2) * cw) : zp - T(0.5) * cw;
  const T push = kc * h1 / d;
  const T tx = push * t * rx, ty = push * t * ry;      // the end node's share, and the start node's rest
  F[(2 * k) * S] += push * rx - tx;
  F[(2 * k + 1) * S] += push * ry - ty;
  F[(2 * k + 2) * S] += tx;
  F[(2 * k + 3) * S] += ty;
  return -z;
}

// Adds the contact forces at x into F (both stride S) over the candidate pairs.
template <int S, typename T>
inline void contact_forces(const Scalars& s, const T* x, const T* pegs, const std::vector<PegPair>& pairs,
                           int64_t lift, T* F) {
  const T rr = T(s.rr), kc = T(s.kc), cw = T(s.cw);
  for (const PegPair& pr : pairs) {
    const int64_t k = pr.k;
    if (k == lift || k + 1 == lift) continue;
    const T* peg = pegs + 3 * pr.j;
    const T reach = peg[2] + rr;
    if (!peg_near(x[(2 * k) * S], x[(2 * k + 1) * S], x[(2 * k + 2) * S], x[(2 * k + 3) * S], peg[0], peg[1],
                  reach * reach))
      continue;
    peg_force<S>(rr, kc, cw, x, peg, k, F);
  }
}

// Adds the contact energy's Hessian-vector product H_c u at x into out (x, u, out stride S); returns u . F_c(x).
// For one pair, g_a = -k_c H' (1 - t) n, g_b = -k_c H' t n; along (ua, ub), ue = ub - ua: dt = 0 where s is clamped,
// else [-ua.e + (c - a).ue - 2 s e.ue] / e.e; dq = (1 - t) ua + t ub + e dt, dz = -n.dq, dn = (dq - n (n.dq)) / d;
// dg_a = -k_c [H'' dz (1 - t) n - H' dt n + H' (1 - t) dn], dg_b = -k_c [H'' dz t n + H' dt n + H' t dn].
template <int S, typename T>
inline T contact_hvp(const Scalars& s, const T* x, const T* pegs, const std::vector<PegPair>& pairs, int64_t lift,
                     const T* u, T* out) {
  const T rr = T(s.rr), kc = T(s.kc), cw = T(s.cw);
  T dot = 0;
  for (const PegPair& pr : pairs) {
    const int64_t k = pr.k;
    if (k == lift || k + 1 == lift) continue;
    const T ax = x[(2 * k) * S], ay = x[(2 * k + 1) * S], bx = x[(2 * k + 2) * S], by = x[(2 * k + 3) * S];
    const T* peg = pegs + 3 * pr.j;
    const T cx = peg[0], cy = peg[1], reach = peg[2] + rr;
    if (!peg_near(ax, ay, bx, by, cx, cy, reach * reach)) continue;
    const T ex = bx - ax, ey = by - ay;
    T sv, t, rx, ry, d, z;
    peg_closest(ax, ay, ex, ey, cx, cy, reach, sv, t, rx, ry, d, z);
    if (!(z > T(0))) continue;
    const T uax = u[(2 * k) * S], uay = u[(2 * k + 1) * S], ubx = u[(2 * k + 2) * S], uby = u[(2 * k + 3) * S];
    const T uex = ubx - uax, uey = uby - uay;
    const bool ramp = z < cw;
    const T h1 = ramp ? z * z / (T(2) * cw) : z - T(0.5) * cw;
    const T h2 = ramp ? z / cw : T(1);
    const T nx = rx / d, ny = ry / d;
    const T dt = sv > T(0) && sv < T(1)
                     ? (-(uax * ex + uay * ey) + (cx - ax) * uex + (cy - ay) * uey - T(2) * sv * (ex * uex + ey * uey)) /
                           (ex * ex + ey * ey)
                     : T(0);
    const T mt = T(1) - t;
    const T dqx = mt * uax + t * ubx + ex * dt, dqy = mt * uay + t * uby + ey * dt;
    const T nd = nx * dqx + ny * dqy;
    const T dnx = (dqx - nx * nd) / d, dny = (dqy - ny * nd) / d;
    const T c2 = -kc * h2 * nd, c1 = kc * h1;          // k_c H'' dz, k_c H'
    out[(2 * k) * S] -= (c2 * mt - c1 * dt) * nx + c1 * mt * dnx;
    out[(2 * k + 1) * S] -= (c2 * mt - c1 * dt) * ny + c1 * mt * dny;
    out[(2 * k + 2) * S] -= (c2 * t + c1 * dt) * nx + c1 * t * dnx;
    out[(2 * k + 3) * S] -= (c2 * t + c1 * dt) * ny + c1 * t * dny;
    dot += c1 * (mt * (uax * nx + uay * ny) + t * (ubx * nx + uby * ny));
  }
  return dot;
}

// One substep; with K > 0 pegs (lift: the grasped node whose links are lifted, -1 none) the contact forces too.
template <typename T>
inline void substep(const Scalars& s, int64_t n, T* x, T* v, Work<T>& w, const T* pegs = nullptr, int64_t K = 0,
                    int64_t lift = -1) {
  forces(s, n, x, w);
  if (K > 0) {
    peg_list_update(s, n, x, pegs, K, w.pegs);
    contact_forces<1>(s, x, pegs, w.pegs.pairs, lift, w.F.data());
  }
  const T h = T(s.h), hm = T(s.h * s.inv_m), damp = T(s.damp);
  for (int64_t i = 0; i < 2 * n; ++i) {
    v[i] = (v[i] + hm * w.F[i]) * damp;
    x[i] += h * v[i];
  }
}

// Reference position/velocity of the grasped node at drag substep k (control.reference): the velocity is the
// path's displacement over the substep / h, continuous in the drag d.
template <typename T>
inline T path_fraction(const T* d, T speed, int64_t k, T h) {
  const T safe = std::max(std::sqrt(d[0] * d[0] + d[1] * d[1]), T(1e-12));
  return std::min(T(k) * h * speed / safe, T(1));
}

template <typename T>
inline void reference(const T* start, const T* d, T speed, int64_t k, T h, T* ref, T* refv) {
  const T frac = path_fraction(d, speed, k, h), prev = path_fraction(d, speed, k - 1, h);
  for (int c = 0; c < 2; ++c) {
    ref[c] = start[c] + frac * d[c];
    refv[c] = (frac - prev) / h * d[c];
  }
}

// Adjoint of reference(): a, c are the adjoints of ref and refv; accumulates into gd (drag) and gstart.
// frac_j = min(1, j h s / |d|) with s = vmax (slow: d frac_j / d d = -frac_j u / |d| while unclamped) or
// s = |d| / (max_drag h) (fast: frac_j = j / max_drag, constant).
template <typename T>
inline void reference_adjoint(const T* d, T speed, int64_t k, T h, T vmax, const T* a, const T* c, T* gd,
                              T* gstart) {
  const T safe = std::max(std::sqrt(d[0] * d[0] + d[1] * d[1]), T(1e-12));
  const T ux = d[0] / safe, uy = d[1] / safe;
  const bool slow = !(speed > vmax);
  const T raw = T(k) * h * speed / safe, raw_prev = T(k - 1) * h * speed / safe;
  const T frac = std::min(raw, T(1)), frac_prev = std::min(raw_prev, T(1));
  const T dfrac = slow && raw < T(1) ? -raw / safe : T(0);             // d frac / d d = dfrac * u
  const T dprev = slow && raw_prev < T(1) ? -raw_prev / safe : T(0);
  const T adot = a[0] * d[0] + a[1] * d[1], cdot = c[0] * d[0] + c[1] * d[1];
  for (int i = 0; i < 2; ++i) {
    const T u = i == 0 ? ux : uy;
    gd[i] += frac * a[i] + adot * dfrac * u + ((frac - frac_prev) * c[i] + cdot * (dfrac - dprev) * u) / h;
    gstart[i] += a[i];
  }
}

// Run one rope. Returns the number of substeps done; if traj != nullptr stores x_0..x_K (n*2 each), if vtraj
// v_0..v_K, if frames the frames x_0, x_E, x_2E, ... (E = in.record_every) up to x_K. pegs: the rope's K pegs
// (x, y, R); pin: the pinned node (-1: none).
template <typename T>
int64_t run_rope(const Scalars& s, const Ints& in, T* x, T* v, int64_t g, const T* d, T speed, int64_t n_grasp,
                 T* traj, T* betas, int64_t* settled, int64_t* diverged, Work<T>& w, T* vtraj = nullptr,
                 T* frames = nullptr, const T* pegs = nullptr, int64_t K = 0, int64_t pin = -1) {
  const int64_t n = in.n;
  const T h = T(s.h);
  T start[2] = {x[2 * g], x[2 * g + 1]};
  const T pstart[2] = {pin >= 0 ? x[2 * pin] : T(0), pin >= 0 ? x[2 * pin + 1] : T(0)};
  T ref[2], refv[2];
  *settled = 0;
  *diverged = 0;
  if (traj) std::copy(x, x + 2 * n, traj);
  if (vtraj) std::copy(v, v + 2 * n, vtraj);
  if (frames) std::copy(x, x + 2 * n, frames);
  auto bad = [&]() {
    for (int64_t i = 0; i < 2 * n; ++i)
      if (!std::isfinite(x[i]) || std::abs(x[i]) > T(s.radius)) return true;
    return false;
  };
  const T phi = in.fixed_steps >= 0 ? T(1) : last_share(d, speed, n_grasp, h, T(s.vmax), w.dphi);
  const int64_t cap_at = std::max<int64_t>(1, n_grasp + in.max_settle);
  w.phi = phi;
  w.lerped = false;
  for (int64_t k = 1;; ++k) {
    if (phi < T(1) && k == cap_at) {
      std::copy(x, x + 2 * n, w.xprev.begin());
      std::copy(v, v + 2 * n, w.vprev.begin());
    }
    substep(s, n, x, v, w, pegs, K, k <= n_grasp ? g : int64_t(-1));
    if (betas) std::copy(w.beta.begin(), w.beta.end(), betas + (n - 2) * (k - 1));   // beta(x_{k-1})
    if (k <= n_grasp) {
      if (pin >= 0) {                     // held at its start with velocity 0, released as the grasp
        T* xp = x + 2 * pin;
        T* vp = v + 2 * pin;
        if (k == n_grasp && phi < T(1)) {
          T* f = w.pfree;
          f[0] = xp[0], f[1] = xp[1], f[2] = vp[0], f[3] = vp[1];
          xp[0] = f[0] + phi * (pstart[0] - f[0]);
          xp[1] = f[1] + phi * (pstart[1] - f[1]);
          vp[0] = f[2] + phi * (T(0) - f[2]);
          vp[1] = f[3] + phi * (T(0) - f[3]);
        } else {
          xp[0] = pstart[0];
          xp[1] = pstart[1];
          vp[0] = vp[1] = T(0);
        }
      }
      reference(start, d, speed, k, h, ref, refv);
      if (k == n_grasp && phi < T(1)) {
        T* f = w.free;
        f[0] = x[2 * g], f[1] = x[2 * g + 1], f[2] = v[2 * g], f[3] = v[2 * g + 1];
        x[2 * g] = f[0] + phi * (ref[0] - f[0]);
        x[2 * g + 1] = f[1] + phi * (ref[1] - f[1]);
        v[2 * g] = f[2] + phi * (refv[0] - f[2]);
        v[2 * g + 1] = f[3] + phi * (refv[1] - f[3]);
      } else {
        x[2 * g] = ref[0];
        x[2 * g + 1] = ref[1];
        v[2 * g] = refv[0];
        v[2 * g + 1] = refv[1];
      }
    }
    if (traj) std::copy(x, x + 2 * n, traj + 2 * n * k);
    if (vtraj) std::copy(v, v + 2 * n, vtraj + 2 * n * k);
    if (frames && k % in.record_every == 0) std::copy(x, x + 2 * n, frames + 2 * n * (k / in.record_every));
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
      if (capped) {
        if (phi < T(1)) {
          std::copy(x, x + 2 * n, w.xcap.begin());
          std::copy(v, v + 2 * n, w.vcap.begin());
          for (int64_t i = 0; i < 2 * n; ++i) {
            x[i] = w.xprev[i] + phi * (x[i] - w.xprev[i]);
            v[i] = w.vprev[i] + phi * (v[i] - w.vprev[i]);
          }
          w.lerped = true;
          if (frames && k % in.record_every == 0) std::copy(x, x + 2 * n, frames + 2 * n * (k / in.record_every));
        }
        return k;
      }
    }
  }
}


// ------------------------------------------------------------------------------------------------------------
// Lane groups: W ropes in lockstep, batch index innermost (array[(row * W) + lane]), so the compiler vectorizes
// every per-node loop across ropes. Same scheme as the per-rope path above; a lane whose rope has finished is
// frozen by selects. Used for full groups of W ropes; the remaining ropes take the per-rope path.
constexpr int W = 16;   // 16 floats = one AVX-512 vector (two AVX2 vectors); measured 1.5x over 8

// Branch-free atan2 (Cephes atan rational approximation; within ~1 ulp of std::atan2, same signed zeros).
template <typename T>
inline T fast_atan2(T y, T x) {
  const T ax = std::abs(x), ay = std::abs(y);
  const bool swap = ay > ax;
  const T num = swap ? ax : ay, den = swap ? ay : ax;
  T t = den > T(0) ? num / den : T(0);
  const bool big = t > T(0.66);
  const T base = big ? T(0.78539816339744830962) : T(0);
  const T more = big ? T(0.5 * 6.123233995736765886130E-17) : T(0);
  t = big ? (t - T(1)) / (t + T(1)) : t;
  const T z = t * t;
  const T p = (((T(-8.750608600031904122785E-1) * z + T(-1.615753718733365076637E1)) * z
               + T(-7.500855792314704667340E1)) * z + T(-1.228866684490136173410E2)) * z
               + T(-6.485021904942025371773E1);
  const T q = ((((z + T(2.485846490142306297962E1)) * z + T(1.650270098316988542046E2)) * z
               + T(4.328810604912902668951E2)) * z + T(4.853903996359136964868E2)) * z
               + T(1.945506571482613964425E2);
  T r = base + (t * (z * p / q) + t + more);
  r = swap ? T(1.57079632679489661923) - r + T(6.123233995736765886130E-17) : r;
  r = std::signbit(x) ? T(3.14159265358979323846) - r + T(1.2246467991473532e-16) : r;
  return std::copysign(r, y);
}

// Scratch of one lane group. Border rows are zero padding, so the inner loops need no conditionals:
// bp (n rows): bp[0] = bp[n-1] = 0, bp[j + 1] = turning angle at interior node j + 1; link k uses bp[k], bp[k+1].
// Gp (2 (n + 1) rows): Gp rows of link k at k + 1, zero rows for the missing links -1 and n - 1.
template <typename T>
struct GroupWork {
  std::vector<T> e, len2, bp, Gp, F, we, dbp;
  // the release of each lane, as Work's (in group layout)
  T phi[W], dphi[W][2], free[W][4], pfree[W][4];
  bool lerped[W];
  std::vector<T> xprev, vprev, xcap, vcap;
  // the contact's candidate pairs of each lane (group_peg_lists), built at the references pref (group layout)
  std::vector<T> pref, pscratch;
  std::vector<PegPair> pairs[W];
  // the due pairs of a forward substep, gathered for one vectorized evaluation (group_contact_forces)
  std::vector<T> batch;
  std::vector<int64_t> boff;
  std::vector<PegPair*> bpair;
  std::vector<int> blane;
  bool pbuilt[W] = {};
  double pdue[W] = {};        // the earliest due travel of each lane's pairs (group_contact_forces)
  explicit GroupWork(int64_t n) : e(2 * (n - 1) * W), len2((n - 1) * W), bp(n * W, T(0)), Gp(2 * (n + 1) * W, T(0)),
                                  F(2 * n * W), we(2 * (n - 1) * W), dbp(n * W, T(0)), xprev(2 * n * W),
                                  vprev(2 * n * W), xcap(2 * n * W), vcap(2 * n * W), pref(2 * n * W, T(0)),
                                  pscratch(3 * n) {}
};

template <typename T>
inline void group_links(int64_t n, const T* __restrict x, T* __restrict e, T* __restrict len2) {
  for (int64_t k = 0; k < n - 1; ++k) {
    const T* __restrict x0 = x + 2 * k * W;
    T* __restrict ek = e + 2 * k * W;
    for (int l = 0; l < W; ++l) {
      const T ex = x0[2 * W + l] - x0[l];
      const T ey = x0[3 * W + l] - x0[W + l];
      ek[l] = ex;
      ek[W + l] = ey;
      len2[k * W + l] = ex * ex + ey * ey;
    }
  }
}

// Per-lane physics of a group: the same numbers the per-rope path computes from its Scalars (rope_scalars), so a
// rope gets identical arithmetic in either path and, without per-rope physics, the scalars of fp[] in every lane.
template <typename T>
struct LanePhys {
  T ks[W], kb[W], hm[W], damp[W], coef[W], inv_m[W];
  LanePhys(const Scalars& s, const double* phys, int64_t b0) {
    for (int l = 0; l < W; ++l) {
      const Scalars r = rope_scalars(s, phys, b0 + l);
      ks[l] = T(r.ks);
      kb[l] = T(r.kb);
      hm[l] = T(r.h * r.inv_m);
      damp[l] = T(r.damp);
      coef[l] = T(r.h * r.inv_m * r.damp);
      inv_m[l] = T(r.inv_m);
    }
  }
};

// dE/de of every link into Gp (padded) given links, squared lengths and padded angles bp; F = scatter.
template <typename T>
inline void group_link_grad(const Scalars& s, const LanePhys<T>& p, int64_t n, const T* __restrict e,
                            const T* __restrict len2, const T* __restrict bp, T* __restrict Gp) {
  const T l0 = T(s.l0);
  const T* __restrict ks = p.ks;
  const T* __restrict kb = p.kb;
  for (int64_t k = 0; k < n - 1; ++k) {
    const T* __restrict ek = e + 2 * k * W;
    T* __restrict gk = Gp + 2 * (k + 1) * W;
    for (int l = 0; l < W; ++l) {
      const T l2 = len2[k * W + l];
      const T a = ks[l] * (T(1) - l0 / std::sqrt(l2));
      const T b = kb[l] * (bp[k * W + l] - bp[(k + 1) * W + l]) / l2;
      const T ex = ek[l], ey = ek[W + l];
      gk[l] = a * ex - b * ey;
      gk[W + l] = a * ey + b * ex;
    }
  }
}

template <typename T>
inline void group_forces(const Scalars& s, const LanePhys<T>& p, int64_t n, const T* __restrict x,
                         GroupWork<T>& w) {
  T* __restrict e = w.e.data();
  T* __restrict len2 = w.len2.data();
  T* __restrict bp = w.bp.data();
  T* __restrict Gp = w.Gp.data();
  T* __restrict F = w.F.data();
  group_links(n, x, e, len2);
  for (int64_t j = 0; j < n - 2; ++j) {
    const T* __restrict a = e + 2 * j * W;
    T* __restrict bj = bp + (j + 1) * W;
    for (int l = 0; l < W; ++l) {
      const T ax = a[l], ay = a[W + l], bx = a[2 * W + l], by = a[3 * W + l];
      bj[l] = fast_atan2(ax * by - ay * bx, ax * bx + ay * by);
    }
  }
  group_link_grad(s, p, n, e, len2, bp, Gp);
  for (int64_t i = 0; i < 2 * n * W; ++i) F[i] = Gp[i + 2 * W] - Gp[i];     // F_j = G_j - G_{j-1}
}

// (H u) at x with stored padded turning angles bp (n rows of W), into out. If ds, db != nullptr, also per lane
// ds = u . F_s(x), db = u . F_b(x) (see hvp).
template <typename T>
inline void group_hvp(const Scalars& s, const LanePhys<T>& p, int64_t n, const T* __restrict x,
                      const T* __restrict bp, const T* __restrict u, T* __restrict out, GroupWork<T>& w,
                      T* __restrict ds = nullptr, T* __restrict db = nullptr) {
  T* __restrict e = w.e.data();
  T* __restrict len2 = w.len2.data();
  T* __restrict we = w.we.data();
  T* __restrict dbp = w.dbp.data();
  T* __restrict Gp = w.Gp.data();
  group_links(n, x, e, len2);
  group_links(n, u, we, w.F.data());                     // F is free scratch here (perturbation lengths unused)
  for (int64_t j = 0; j < n - 2; ++j) {
    const T* __restrict a = e + 2 * j * W;
    const T* __restrict ua = we + 2 * j * W;
    T* __restrict dj = dbp + (j + 1) * W;
    for (int l = 0; l < W; ++l) {
      const T q1 = (-a[3 * W + l] * ua[2 * W + l] + a[2 * W + l] * ua[3 * W + l]) / len2[(j + 1) * W + l];
      const T q0 = (-a[W + l] * ua[l] + a[l] * ua[W + l]) / len2[j * W + l];
      dj[l] = q1 - q0;
    }
  }
  const T l0 = T(s.l0);
  const T* __restrict ks = p.ks;
  const T* __restrict kb = p.kb;
  for (int64_t k = 0; k < n - 1; ++k) {
    const T* __restrict ek = e + 2 * k * W;
    const T* __restrict uk = we + 2 * k * W;
    T* __restrict gk = Gp + 2 * (k + 1) * W;
    for (int l = 0; l < W; ++l) {
      const T ex = ek[l], ey = ek[W + l], ux = uk[l], uy = uk[W + l];
      const T l2 = len2[k * W + l], len = std::sqrt(l2);
      const T edotu = ex * ux + ey * uy;
      const T a = ks[l] * (T(1) - l0 / len), c = ks[l] * l0 / (len * l2);
      const T db_ = dbp[k * W + l] - dbp[(k + 1) * W + l], bb = bp[k * W + l] - bp[(k + 1) * W + l];
      const T inv = T(1) / l2, two = T(2) * edotu * inv * inv;
      const T qx = -ey * inv, qy = ex * inv;
      const T dqx = -uy * inv + two * ey, dqy = ux * inv - two * ex;
      gk[l] = a * ux + c * edotu * ex + kb[l] * (db_ * qx + bb * dqx);
      gk[W + l] = a * uy + c * edotu * ey + kb[l] * (db_ * qy + bb * dqy);
    }
  }
  for (int64_t i = 0; i < 2 * n * W; ++i) out[i] = Gp[i] - Gp[i + 2 * W];   // (H u)_j = dG_{j-1} - dG_j
  if (ds) {
    for (int l = 0; l < W; ++l) ds[l] = db[l] = T(0);
    for (int64_t k = 0; k < n - 1; ++k) {
      const T* __restrict ek = e + 2 * k * W;
      const T* __restrict uk = we + 2 * k * W;
      for (int l = 0; l < W; ++l) {
        const T ex = ek[l], ey = ek[W + l], ux = uk[l], uy = uk[W + l];
        const T l2 = len2[k * W + l];
        const T bb = bp[k * W + l] - bp[(k + 1) * W + l];
        ds[l] -= (T(1) - l0 / std::sqrt(l2)) * (ex * ux + ey * uy);
        db[l] -= bb / l2 * (-ey * ux + ex * uy);
      }
    }
  }
}

struct Lane {          // per-lane action and run record
  int64_t g, n_grasp, steps, settled, diverged;
  bool active;
  int64_t pin;         // the pinned node, -1: none
};

// The candidate lists of a lane group's ropes (see peg_list_update), valid at x afterwards for the lanes with
// act[l] != 0: the displacement from the references runs across the lanes, the rebuild per lane. pegs: the group's
// first rope's pegs (K rows of (x, y, R) per rope, as the batch holds them).
template <typename T>
inline void group_peg_lists(const Scalars& s, int64_t n, const T* __restrict x, const T* pegs, int64_t K,
                            const T* act, GroupWork<T>& w) {
  const T skin = peg_skin<T>(s), lim = T(0.45 * 0.45) * skin * skin;      // 0.45 skin: a margin for rounding
  const T* __restrict ref = w.pref.data();
  T m[W] = {};
  for (int64_t i = 0; i < n; ++i) {
    const T* __restrict xi = x + 2 * i * W;
    const T* __restrict ri = ref + 2 * i * W;
    for (int l = 0; l < W; ++l) {
      const T dx = xi[l] - ri[l], dy = xi[W + l] - ri[W + l];
      m[l] = std::max(m[l], dx * dx + dy * dy);
    }
  }
  for (int l = 0; l < W; ++l) {
    if (act[l] == T(0) || (w.pbuilt[l] && m[l] <= lim)) continue;
    peg_pairs<W>(n, x + l, pegs + 3 * K * l, K, T(s.rr), skin, w.pscratch.data(), w.pairs[l]);
    for (int64_t i = 0; i < 2 * n; ++i) w.pref[i * W + l] = x[i * W + l];
    w.pbuilt[l] = true;
  }
}

// As group_peg_lists, for the forward run (run_group): clock[l] - built_at[l] bounds how far any node of lane l has
// moved since its list was built (clock: the sum of the lane's substeps' longest node step). Where it exceeds
// 0.45 skin (< skin / 2, a margin for rounding) the nodes' displacement from where the list was built is measured
// (the clock overestimates it where the rope jitters): the list is rebuilt if that exceeds the limit too, else
// the clock's bound restarts from it.
template <typename T>
inline void group_peg_lists_clocked(const Scalars& s, int64_t n, const T* x, const T* pegs, int64_t K, const T* act,
                                    const double* clock, double* built_at, GroupWork<T>& w) {
  const T skin = peg_skin<T>(s);
  const double lim = 0.45 * double(skin);
  for (int l = 0; l < W; ++l) {
    if (act[l] == T(0) || (w.pbuilt[l] && clock[l] - built_at[l] <= lim)) continue;
    if (w.pbuilt[l]) {
      T m = 0;
      for (int64_t i = 0; i < 2 * n; i += 2) {
        const T dx = x[i * W + l] - w.pref[i * W + l], dy = x[(i + 1) * W + l] - w.pref[(i + 1) * W + l];
        m = std::max(m, dx * dx + dy * dy);
      }
      const double moved = double(std::sqrt(m)) * (1.0 + 1e-6);
      if (moved <= lim) {
        built_at[l] = clock[l] - moved;
        continue;
      }
    }
    peg_pairs<W>(n, x + l, pegs + 3 * K * l, K, T(s.rr), skin, w.pscratch.data(), w.pairs[l]);
    for (int64_t i = 0; i < 2 * n; ++i) w.pref[i * W + l] = x[i * W + l];
    w.pbuilt[l] = true;
    w.pdue[l] = -1e300;
    built_at[l] = clock[l];
  }
}

// peg_force over a batch of pairs (link a, b; peg c, reach rc): the start node's share (fsx, fsy), the end node's
// (ftx, fty) and the clearance clr.
template <typename T>
inline void peg_force_batch(int64_t m, T kc, T cw, const T* __restrict ax, const T* __restrict ay,
                            const T* __restrict bx, const T* __restrict by, const T* __restrict cx,
                            const T* __restrict cy, const T* __restrict rc, T* __restrict fsx, T* __restrict fsy,
                            T* __restrict ftx, T* __restrict fty, T* __restrict clr) {
  for (int64_t i = 0; i < m; ++i) {
    const T ex = bx[i] - ax[i], ey = by[i] - ay[i];
    const T sv = ((cx[i] - ax[i]) * ex + (cy[i] - ay[i]) * ey) / (ex * ex + ey * ey);
    const T t = sv < T(0) ? T(0) : sv > T(1) ? T(1) : sv;
    const T rx = ax[i] + t * ex - cx[i], ry = ay[i] + t * ey - cy[i];
    const T r2 = rx * rx + ry * ry;
    const T d = std::sqrt(r2 < T(1e-24) ? T(1e-24) : r2);
    const T z = rc[i] - d;
    const T zp = z < T(0) ? T(0) : z;
    const T h1 = zp < cw ? zp * zp / (T(2) * cw) : zp - T(0.5) * cw;
    const T push = kc * h1 / d;
    const T tx = push * t * rx, ty = push * t * ry;
    fsx[i] = push * rx - tx;
    fsy[i] = push * ry - ty;
    ftx[i] = tx;
    fty[i] = ty;
    clr[i] = -z;
  }
}

// The contact forces of the active lanes of a group in its forward run (lift[l]: the lane's lifted node, -1 none),
// into F (group layout), visiting only the pairs that are due: clock[l] is lane l's travel (the sum of its
// substeps' longest node step), and a pair found at clearance c > 0 (distance from the peg less R + r) cannot touch
// before the clock has advanced by c (its link's points move no farther than its nodes), so it is next evaluated
// then (less a margin for rounding); a pair in contact is evaluated every substep. Three passes: the due pairs are
// gathered, their forces computed in one loop across them (as peg_force: it vectorizes, where one pair at a time
// waits on its division and root), then added into F and their next due travel set.
template <typename T>
inline void group_contact_forces(const Scalars& s, const T* x, const T* pegs, int64_t K, const T* act,
                                 const int64_t* lift, const double* clock, double margin, GroupWork<T>& w, T* F) {
  const T rr = T(s.rr), kc = T(s.kc), cw = T(s.cw);
  size_t total = 0;
  for (int l = 0; l < W; ++l) total += w.pairs[l].size();
  if (w.boff.size() < total) {
    w.batch.resize(12 * total);
    w.boff.resize(total);
    w.bpair.resize(total);
    w.blane.resize(total);
  }
  const size_t cap = w.boff.size();
  T* __restrict ax = w.batch.data();
  T* __restrict ay = ax + cap;
  T* __restrict bx = ay + cap;
  T* __restrict by = bx + cap;
  T* __restrict cx = by + cap;
  T* __restrict cy = cx + cap;
  T* __restrict rc = cy + cap;
  T* __restrict fsx = rc + cap;
  T* __restrict fsy = fsx + cap;
  T* __restrict ftx = fsy + cap;
  T* __restrict fty = ftx + cap;
  T* __restrict clr = fty + cap;
  size_t m = 0;
  for (int l = 0; l < W; ++l) {
    if (act[l] == T(0) || clock[l] < w.pdue[l]) continue;     // none of the lane's pairs is due
    const T* lp = pegs + 3 * K * l;
    double first = 1e300;                                       // the earliest due of the pairs not evaluated
    for (PegPair& pr : w.pairs[l]) {
      const int64_t k = pr.k;
      if (clock[l] < pr.due || k == lift[l] || k + 1 == lift[l]) {
        first = std::min(first, pr.due);
        continue;
      }
      const int64_t o = 2 * k * W + l;
      const T* peg = lp + 3 * pr.j;
      ax[m] = x[o], ay[m] = x[o + W], bx[m] = x[o + 2 * W], by[m] = x[o + 3 * W];
      cx[m] = peg[0], cy[m] = peg[1], rc[m] = peg[2] + rr;
      w.boff[m] = o;
      w.bpair[m] = &pr;
      w.blane[m] = l;
      ++m;
    }
    w.pdue[l] = first;
  }
  peg_force_batch(int64_t(m), kc, cw, ax, ay, bx, by, cx, cy, rc, fsx, fsy, ftx, fty, clr);
  for (size_t i = 0; i < m; ++i) {
    T* f = F + w.boff[i];
    f[0] += fsx[i];
    f[W] += fsy[i];
    f[2 * W] += ftx[i];
    f[3 * W] += fty[i];
    const int l = w.blane[i];
    const double due = clr[i] > T(0) ? clock[l] + double(clr[i]) - margin : clock[l];
    w.bpair[i]->due = due;
    w.pdue[l] = std::min(w.pdue[l], due);
  }
}

// Run W ropes in lockstep; x, v in group layout. Returns the substeps of the longest lane. traj, vtraj, betas:
// the trajectory in group layout (for the adjoint); frames: the batch's frame buffer (B, frame_cap, n, 2), into
// which the lanes of ropes b0.. write every record_every substeps (a finished lane writes its frozen state).
// pegs: the K pegs of rope b0, then of the next ropes (as the batch holds them); lane[l].pin the pinned nodes.
template <typename T>
int64_t run_group(const Scalars& s, const LanePhys<T>& p, const Ints& in, T* x, T* v, Lane* lane, const T* d,
                  const T* speed, T* traj, T* betas, GroupWork<T>& w, T* vtraj = nullptr, T* frames = nullptr,
                  int64_t b0 = 0, const T* pegs = nullptr, int64_t K = 0) {
  const int64_t n = in.n, rows = 2 * n;
  const T h = T(s.h);
  const T* __restrict hm = p.hm;
  const T* __restrict damp = p.damp;
  T start[W][2], pstart[W][2], act[W], last[W][2];
  // with pegs: each lane's travel (group_contact_forces) and its value when the lane's list was built, and the
  // longest squared node step of this substep (the grasped node's override included; a pinned node's override
  // step is a share 1 - phi <= 1 of its free step, or 0)
  double clock[W] = {}, built_at[W] = {};
  const double margin = 1e-3 * double(peg_skin<T>(s));
  T dm[W];
  int64_t cap_at[W];
  bool pinned = false;
  for (int l = 0; l < W; ++l) {
    start[l][0] = last[l][0] = x[(2 * lane[l].g) * W + l];
    start[l][1] = last[l][1] = x[(2 * lane[l].g + 1) * W + l];
    const int64_t pn = lane[l].pin;
    pstart[l][0] = pn >= 0 ? x[(2 * pn) * W + l] : T(0);
    pstart[l][1] = pn >= 0 ? x[(2 * pn + 1) * W + l] : T(0);
    pinned = pinned || pn >= 0;
    lane[l].active = true;
    lane[l].settled = lane[l].diverged = 0;
    act[l] = T(1);
    w.phi[l] = in.fixed_steps >= 0 ? T(1) : last_share(d + 2 * l, speed[l], lane[l].n_grasp, h, T(s.vmax), w.dphi[l]);
    w.lerped[l] = false;
    cap_at[l] = std::max<int64_t>(1, lane[l].n_grasp + in.max_settle);
  }
  auto record = [&](int64_t j) {
    for (int l = 0; l < W; ++l) {
      T* dst = frames + ((b0 + l) * in.frame_cap + j) * rows;
      for (int64_t i = 0; i < rows; ++i) dst[i] = x[i * W + l];
    }
  };
  if (traj) std::copy(x, x + rows * W, traj);
  if (vtraj) std::copy(v, v + rows * W, vtraj);
  if (frames) record(0);
  auto bad = [&](int l) {
    for (int64_t i = 0; i < rows; ++i) {
      const T xi = x[i * W + l];
      if (!std::isfinite(xi) || std::abs(xi) > T(s.radius)) return true;
    }
    return false;
  };
  for (int64_t k = 1;; ++k) {
    for (int l = 0; l < W; ++l) {
      if (w.phi[l] < T(1) && k == cap_at[l]) {
        for (int64_t i = 0; i < rows; ++i) {
          w.xprev[i * W + l] = x[i * W + l];
          w.vprev[i * W + l] = v[i * W + l];
        }
      }
    }
    group_forces(s, p, n, x, w);
    const T* __restrict F = w.F.data();
    if (K > 0) {
      group_peg_lists_clocked(s, n, x, pegs, K, act, clock, built_at, w);
      int64_t lift[W];
      for (int l = 0; l < W; ++l) lift[l] = k <= lane[l].n_grasp ? lane[l].g : int64_t(-1);
      group_contact_forces(s, x, pegs, K, act, lift, clock, margin, w, w.F.data());
      for (int l = 0; l < W; ++l) dm[l] = T(0);         // the largest squared step of a node
      for (int64_t j = 0; j < n; ++j) {
        T* __restrict xj = x + 2 * j * W;
        T* __restrict vj = v + 2 * j * W;
        const T* __restrict Fj = F + 2 * j * W;
        for (int l = 0; l < W; ++l) {
          const T vox = vj[l], xox = xj[l], voy = vj[W + l], xoy = xj[W + l];
          const T vnx = (vox + hm[l] * Fj[l]) * damp[l], vny = (voy + hm[l] * Fj[W + l]) * damp[l];
          const T xnx = xox + h * vnx, xny = xoy + h * vny;
          vj[l] = act[l] != T(0) ? vnx : vox;
          xj[l] = act[l] != T(0) ? xnx : xox;
          vj[W + l] = act[l] != T(0) ? vny : voy;
          xj[W + l] = act[l] != T(0) ? xny : xoy;
          const T dx = xnx - xox, dy = xny - xoy;
          dm[l] = std::max(dm[l], dx * dx + dy * dy);
        }
      }
    } else {
      for (int64_t i = 0; i < rows; ++i) {
        T* __restrict xi = x + i * W;
        T* __restrict vi = v + i * W;
        for (int l = 0; l < W; ++l) {
          const T vo = vi[l], xo = xi[l];
          const T vn = (vo + hm[l] * F[i * W + l]) * damp[l];
          const T xn = xo + h * vn;
          vi[l] = act[l] != T(0) ? vn : vo;
          xi[l] = act[l] != T(0) ? xn : xo;
        }
      }
    }
    if (betas) std::copy(w.bp.begin(), w.bp.end(), betas + n * W * (k - 1));
    for (int l = 0; pinned && l < W; ++l) {      // the pins (see run_rope)
      const int64_t pn = lane[l].pin;
      if (pn < 0 || !lane[l].active || k > lane[l].n_grasp) continue;
      T* xp = x + (2 * pn) * W + l;
      T* vp = v + (2 * pn) * W + l;
      const T phi = w.phi[l];
      if (k == lane[l].n_grasp && phi < T(1)) {
        T* f = w.pfree[l];
        f[0] = xp[0], f[1] = xp[W], f[2] = vp[0], f[3] = vp[W];
        xp[0] = f[0] + phi * (pstart[l][0] - f[0]);
        xp[W] = f[1] + phi * (pstart[l][1] - f[1]);
        vp[0] = f[2] + phi * (T(0) - f[2]);
        vp[W] = f[3] + phi * (T(0) - f[3]);
      } else {
        xp[0] = pstart[l][0];
        xp[W] = pstart[l][1];
        vp[0] = vp[W] = T(0);
      }
    }
    for (int l = 0; l < W; ++l) {
      if (lane[l].active && k <= lane[l].n_grasp) {
        T ref[2], refv[2];
        reference(start[l], d + 2 * l, speed[l], k, h, ref, refv);
        const int64_t g = lane[l].g;
        T* xg = x + (2 * g) * W + l;          // xg[0], xg[W]: the node's x, y
        T* vg = v + (2 * g) * W + l;
        const T phi = w.phi[l];
        if (k == lane[l].n_grasp && phi < T(1)) {
          T* f = w.free[l];
          f[0] = xg[0], f[1] = xg[W], f[2] = vg[0], f[3] = vg[W];
          xg[0] = f[0] + phi * (ref[0] - f[0]);
          xg[W] = f[1] + phi * (ref[1] - f[1]);
          vg[0] = f[2] + phi * (refv[0] - f[2]);
          vg[W] = f[3] + phi * (refv[1] - f[3]);
        } else {
          xg[0] = ref[0];
          xg[W] = ref[1];
          vg[0] = refv[0];
          vg[W] = refv[1];
        }
        if (K > 0) {                          // the override's step from the node's previous override
          const T sx = xg[0] - last[l][0], sy = xg[W] - last[l][1];
          dm[l] = std::max(dm[l], sx * sx + sy * sy);
          last[l][0] = xg[0], last[l][1] = xg[W];
        }
      }
    }
    if (K > 0)
      for (int l = 0; l < W; ++l) clock[l] += double(std::sqrt(dm[l]));
    if (traj) std::copy(x, x + rows * W, traj + rows * W * k);
    if (vtraj) std::copy(v, v + rows * W, vtraj + rows * W * k);
    if (frames && k % in.record_every == 0) record(k / in.record_every);
    bool any = false;
    for (int l = 0; l < W; ++l) {
      if (!lane[l].active) continue;
      bool stop = false;
      if (in.fixed_steps >= 0) {
        if (k >= in.fixed_steps) {
          lane[l].diverged = bad(l);
          stop = true;
        }
      } else {
        const int64_t since = k - lane[l].n_grasp;
        const bool check = since > 0 && since % in.check_every == 0;
        const bool capped = since >= in.max_settle;
        if (check || capped) {
          if (bad(l)) {
            lane[l].diverged = 1;
            stop = true;
          } else if (check) {
            T vmax2 = 0;
            for (int64_t j = 0; j < n; ++j) {
              const T vx = v[(2 * j) * W + l], vy = v[(2 * j + 1) * W + l];
              vmax2 = std::max(vmax2, vx * vx + vy * vy);
            }
            if (std::sqrt(vmax2) < T(s.threshold)) {
              lane[l].settled = 1;
              stop = true;
            }
          }
          if (capped && !stop && w.phi[l] < T(1)) {
            const T phi = w.phi[l];
            for (int64_t i = 0; i < rows; ++i) {
              const int64_t j = i * W + l;
              w.xcap[j] = x[j];
              w.vcap[j] = v[j];
              x[j] = w.xprev[j] + phi * (x[j] - w.xprev[j]);
              v[j] = w.vprev[j] + phi * (v[j] - w.vprev[j]);
            }
            w.lerped[l] = true;
            if (frames && k % in.record_every == 0) {
              T* dst = frames + ((b0 + l) * in.frame_cap + k / in.record_every) * rows;
              for (int64_t i = 0; i < rows; ++i) dst[i] = x[i * W + l];
            }
          }
          stop = stop || capped;
        }
      }
      if (stop) {
        lane[l].active = false;
        lane[l].steps = k;
        act[l] = T(0);
      } else {
        any = true;
      }
    }
    if (!any) return k;
  }
}

template <typename T>
void to_group(int64_t n, const T* src, int64_t b0, T* dst) {     // (W, n, 2) rows of the batch -> group layout
  for (int l = 0; l < W; ++l)
    for (int64_t i = 0; i < 2 * n; ++i) dst[i * W + l] = src[(b0 + l) * 2 * n + i];
}

template <typename T>
void from_group(int64_t n, const T* src, int64_t b0, T* dst) {
  for (int l = 0; l < W; ++l)
    for (int64_t i = 0; i < 2 * n; ++i) dst[(b0 + l) * 2 * n + i] = src[i * W + l];
}

template <typename T>
void forward_group(const Scalars& s, const Ints& in, int64_t b0, const T* pos, const T* vel, const int64_t* node,
                   const T* delta, const T* speed, const int64_t* n_grasp, const double* phys, const T* pegs,
                   int64_t K, const int64_t* pin, T* out_pos, T* out_vel, int64_t* out_steps, int64_t* out_settled,
                   int64_t* out_diverged, T* frames) {
  const int64_t n = in.n;
  GroupWork<T> w(n);
  const LanePhys<T> p(s, phys, b0);
  std::vector<T> x(2 * n * W), v(2 * n * W, T(0));
  to_group(n, pos, b0, x.data());
  if (vel) to_group(n, vel, b0, v.data());
  Lane lane[W];
  for (int l = 0; l < W; ++l)
    lane[l] = Lane{node[b0 + l], n_grasp[b0 + l], 0, 0, 0, true, pin ? pin[b0 + l] : int64_t(-1)};
  run_group(s, p, in, x.data(), v.data(), lane, delta + 2 * b0, speed + b0, static_cast<T*>(nullptr),
            static_cast<T*>(nullptr), w, static_cast<T*>(nullptr), frames, b0, K > 0 ? pegs + 3 * K * b0 : nullptr, K);
  from_group(n, x.data(), b0, out_pos);
  from_group(n, v.data(), b0, out_vel);
  for (int l = 0; l < W; ++l) {
    out_steps[b0 + l] = lane[l].steps;
    out_settled[b0 + l] = lane[l].settled;
    out_diverged[b0 + l] = lane[l].diverged;
  }
}

template <typename T>
void backward_group(const Scalars& s, const Ints& in, int64_t b0, const T* pos, const T* vel, const int64_t* node,
                    const T* delta, const T* speed, const int64_t* n_grasp, const double* phys, const T* pegs,
                    int64_t n_pegs, const int64_t* pin, const T* grad_out_pos, const T* grad_out_vel,
                    const T* grad_frames, T* grad_pos, T* grad_vel, T* grad_delta, T* grad_phys) {
  const int64_t n = in.n, rows = 2 * n;
  const int64_t max_steps = in.fixed_steps >= 0 ? in.fixed_steps : in.max_drag + in.max_settle + 1;
  GroupWork<T> w(n);
  const LanePhys<T> p(s, phys, b0);
  std::unique_ptr<T[]> traj(new T[rows * W * (max_steps + 2)]), betas(new T[n * W * (max_steps + 1)]);
  std::unique_ptr<T[]> vtraj(grad_phys ? new T[rows * W * (max_steps + 2)] : nullptr);
  std::vector<T> x(rows * W), v(rows * W, T(0)), gx(rows * W), gv(rows * W, T(0)), u(rows * W), hu(rows * W);
  to_group(n, pos, b0, x.data());
  if (vel) to_group(n, vel, b0, v.data());
  Lane lane[W];
  for (int l = 0; l < W; ++l)
    lane[l] = Lane{node[b0 + l], n_grasp[b0 + l], 0, 0, 0, true, pin ? pin[b0 + l] : int64_t(-1)};
  const T* gpegs = n_pegs > 0 ? pegs + 3 * n_pegs * b0 : nullptr;
  const T* d = delta + 2 * b0;
  const T* sp = speed + b0;
  const int64_t K = run_group(s, p, in, x.data(), v.data(), lane, d, sp, traj.get(), betas.get(), w, vtraj.get(),
                              static_cast<T*>(nullptr), b0, gpegs, n_pegs);
  to_group(n, grad_out_pos, b0, gx.data());
  if (grad_out_vel) to_group(n, grad_out_vel, b0, gv.data());
  const T h = T(s.h), vmax = T(s.vmax);
  const T* __restrict damp = p.damp;
  const T* __restrict coef = p.coef;
  T gd[W][2] = {}, gstart[W][2] = {}, gpin[W][2] = {}, act[W], gphi[W] = {};
  // the release (see run_group): a lane stopped by the cap returned x_prev + phi (x_K - x_prev)
  std::vector<T> gout_x(gx), gout_v(gv);
  auto frame_at_end = [&](int l) { return grad_frames && w.lerped[l] && lane[l].steps % in.record_every == 0; };
  for (int l = 0; l < W; ++l) {
    if (!w.lerped[l]) continue;
    const T phi = w.phi[l];
    if (frame_at_end(l)) {                  // that frame is the lane's x_out too
      const T* gf = grad_frames + ((b0 + l) * in.frame_cap + lane[l].steps / in.record_every) * rows;
      for (int64_t i = 0; i < rows; ++i) gx[i * W + l] = gout_x[i * W + l] += gf[i];
    }
    for (int64_t i = 0; i < rows; ++i) {
      const int64_t j = i * W + l;
      gphi[l] += gout_x[j] * (w.xcap[j] - w.xprev[j]) + gout_v[j] * (w.vcap[j] - w.vprev[j]);
      gx[j] *= phi;
      gv[j] *= phi;
    }
  }
  T ds[W], db[W], dc[W], acc_s[W] = {}, acc_b[W] = {}, acc_c[W] = {}, acc_w[W] = {}, uv[W];
  // frame j of lane l's rope, when its gradient is injected at substep j * record_every
  auto frame_grad = [&](int l, int64_t j) { return grad_frames + ((b0 + l) * in.frame_cap + j) * rows; };
  for (int64_t k = K; k >= 1; --k) {
    const bool on_frame = grad_frames && k % in.record_every == 0;
    for (int l = 0; l < W; ++l) {
      act[l] = k <= lane[l].steps ? T(1) : T(0);
      if (k > lane[l].steps) continue;
      if (on_frame && !(k == lane[l].steps && frame_at_end(l))) {
        const T* gf = frame_grad(l, k / in.record_every);
        for (int64_t i = 0; i < rows; ++i) gx[i * W + l] += gf[i];
      }
      if (k > lane[l].n_grasp) continue;
      const T phi = w.phi[l];
      if (lane[l].pin >= 0) {                         // the pin (see backward)
        T* xp = gx.data() + (2 * lane[l].pin) * W + l;
        T* vp = gv.data() + (2 * lane[l].pin) * W + l;
        if (k == lane[l].n_grasp && phi < T(1)) {
          const T* ps = pos + (b0 + l) * rows + 2 * lane[l].pin;
          const T* f = w.pfree[l];
          gphi[l] += xp[0] * (ps[0] - f[0]) + xp[W] * (ps[1] - f[1]) + vp[0] * (T(0) - f[2]) + vp[W] * (T(0) - f[3]);
          gpin[l][0] += phi * xp[0];
          gpin[l][1] += phi * xp[W];
          xp[0] *= T(1) - phi, xp[W] *= T(1) - phi, vp[0] *= T(1) - phi, vp[W] *= T(1) - phi;
        } else {
          gpin[l][0] += xp[0];
          gpin[l][1] += xp[W];
          xp[0] = xp[W] = vp[0] = vp[W] = T(0);
        }
      }
      const int64_t g = lane[l].g;
      T a[2] = {gx[(2 * g) * W + l], gx[(2 * g + 1) * W + l]}, c[2] = {gv[(2 * g) * W + l], gv[(2 * g + 1) * W + l]};
      if (k == lane[l].n_grasp && phi < T(1)) {       // node = free + phi (reference - free)
        T start[2] = {pos[(b0 + l) * rows + 2 * g], pos[(b0 + l) * rows + 2 * g + 1]}, ref[2], refv[2];
        reference(start, d + 2 * l, sp[l], k, h, ref, refv);
        const T* f = w.free[l];
        gphi[l] += a[0] * (ref[0] - f[0]) + a[1] * (ref[1] - f[1]) + c[0] * (refv[0] - f[2]) + c[1] * (refv[1] - f[3]);
        T pa[2] = {phi * a[0], phi * a[1]}, pc[2] = {phi * c[0], phi * c[1]};
        reference_adjoint(d + 2 * l, sp[l], k, h, vmax, pa, pc, gd[l], gstart[l]);
        gx[(2 * g) * W + l] = (T(1) - phi) * a[0];
        gx[(2 * g + 1) * W + l] = (T(1) - phi) * a[1];
        gv[(2 * g) * W + l] = (T(1) - phi) * c[0];
        gv[(2 * g + 1) * W + l] = (T(1) - phi) * c[1];
      } else {
        reference_adjoint(d + 2 * l, sp[l], k, h, vmax, a, c, gd[l], gstart[l]);
        gx[(2 * g) * W + l] = gx[(2 * g + 1) * W + l] = gv[(2 * g) * W + l] = gv[(2 * g + 1) * W + l] = T(0);
      }
    }
    for (int64_t i = 0; i < rows * W; ++i) u[i] = gv[i] + h * gx[i];
    group_hvp(s, p, n, traj.get() + rows * W * (k - 1), betas.get() + n * W * (k - 1), u.data(), hu.data(), w,
              grad_phys ? ds : static_cast<T*>(nullptr), grad_phys ? db : static_cast<T*>(nullptr));
    if (n_pegs > 0) {
      const T* xk = traj.get() + rows * W * (k - 1);
      group_peg_lists(s, n, xk, gpegs, n_pegs, act, w);
      for (int l = 0; l < W; ++l)
        dc[l] = act[l] != T(0) ? contact_hvp<W>(s, xk + l, gpegs + 3 * n_pegs * l, w.pairs[l],
                                                k <= lane[l].n_grasp ? lane[l].g : int64_t(-1), u.data() + l,
                                                hu.data() + l)
                               : T(0);
    }
    if (grad_phys) {
      // d v_k = damp [(v_{k-1} + h/m F) d damp/damp + h d(1/m) F + h/m (d k_s F_s + d k_b F_b)], F = k_s F_s + k_b F_b
      const T* __restrict vk = vtraj.get() + rows * W * (k - 1);
      for (int l = 0; l < W; ++l) uv[l] = T(0);
      for (int64_t i = 0; i < rows; ++i)
        for (int l = 0; l < W; ++l) uv[l] += u[i * W + l] * vk[i * W + l];
      for (int l = 0; l < W; ++l) {
        if (act[l] == T(0)) continue;
        acc_s[l] += ds[l];
        acc_b[l] += db[l];
        if (n_pegs > 0) {        // the contact force F_c enters 1/m and damp as the internal one does
          acc_c[l] += dc[l];
          acc_w[l] += uv[l] + h * p.inv_m[l] * (p.ks[l] * ds[l] + p.kb[l] * db[l] + dc[l]);
        } else {
          acc_w[l] += uv[l] + h * p.inv_m[l] * (p.ks[l] * ds[l] + p.kb[l] * db[l]);
        }
      }
    }
    for (int64_t i = 0; i < rows; ++i) {
      T* __restrict gxi = gx.data() + i * W;
      T* __restrict gvi = gv.data() + i * W;
      const T* __restrict ui = u.data() + i * W;
      const T* __restrict hui = hu.data() + i * W;
      for (int l = 0; l < W; ++l) {
        const T gxo = gxi[l], gvo = gvi[l];
        gxi[l] = act[l] != T(0) ? gxo - coef[l] * hui[l] : gxo;
        gvi[l] = act[l] != T(0) ? damp[l] * ui[l] : gvo;
      }
    }
    for (int l = 0; l < W; ++l) {
      if (!w.lerped[l] || k != lane[l].steps) continue;
      const T rest = T(1) - w.phi[l];
      for (int64_t i = 0; i < rows; ++i) {
        gx[i * W + l] += rest * gout_x[i * W + l];
        gv[i * W + l] += rest * gout_v[i * W + l];
      }
    }
  }
  for (int l = 0; l < W; ++l) {
    if (grad_frames) {
      const T* gf = frame_grad(l, 0);
      for (int64_t i = 0; i < rows; ++i) gx[i * W + l] += gf[i];
    }
    if (lane[l].n_grasp > 0) {
      gx[(2 * lane[l].g) * W + l] += gstart[l][0];
      gx[(2 * lane[l].g + 1) * W + l] += gstart[l][1];
      if (lane[l].pin >= 0) {
        gx[(2 * lane[l].pin) * W + l] += gpin[l][0];
        gx[(2 * lane[l].pin + 1) * W + l] += gpin[l][1];
      }
    }
    grad_delta[2 * (b0 + l)] = gd[l][0] + gphi[l] * w.dphi[l][0];
    grad_delta[2 * (b0 + l) + 1] = gd[l][1] + gphi[l] * w.dphi[l][1];
    if (grad_phys) {
      T* gp = grad_phys + 4 * (b0 + l);
      gp[0] = coef[l] * acc_s[l];
      gp[1] = coef[l] * acc_b[l];
      gp[2] = n_pegs > 0 ? h * damp[l] * (p.ks[l] * acc_s[l] + p.kb[l] * acc_b[l] + acc_c[l])
                         : h * damp[l] * (p.ks[l] * acc_s[l] + p.kb[l] * acc_b[l]);
      gp[3] = acc_w[l];
    }
  }
  from_group(n, gx.data(), b0, grad_pos);
  from_group(n, gv.data(), b0, grad_vel);
}

template <typename T>
void forward(const double* fp, const int64_t* ip, const T* pos, const T* vel, const int64_t* node, const T* delta,
             const T* speed, const int64_t* n_grasp, const double* phys, const T* pegs, int64_t n_pegs,
             const int64_t* pin, T* out_pos, T* out_vel, int64_t* out_steps, int64_t* out_settled,
             int64_t* out_diverged, T* frames) {
  if (!pegs) n_pegs = 0;
  const Scalars s0{fp[0], fp[1], fp[2], fp[3], fp[4], fp[5], fp[6], fp[7], fp[8], fp[9], fp[10], fp[11]};
  const Ints in{ip[0], ip[1], ip[2], ip[3], ip[4], ip[5], ip[6], ip[7], ip[8], ip[9]};
  const int64_t n = in.n;
  const int64_t groups = in.use_groups ? in.B / W : 0, first = groups * W;
  parallel_for(groups + in.B - first, in.threads, [&](int64_t task) {
    if (task < groups) {
      forward_group(s0, in, task * W, pos, vel, node, delta, speed, n_grasp, phys, pegs, n_pegs, pin, out_pos,
                    out_vel, out_steps, out_settled, out_diverged, frames);
      return;
    }
    const int64_t b = first + task - groups;
    const Scalars s = rope_scalars(s0, phys, b);
    Work<T> w(n);
    T* x = out_pos + 2 * n * b;
    T* v = out_vel + 2 * n * b;
    std::copy(pos + 2 * n * b, pos + 2 * n * (b + 1), x);
    if (vel) std::copy(vel + 2 * n * b, vel + 2 * n * (b + 1), v);
    else std::fill(v, v + 2 * n, T(0));
    out_steps[b] = run_rope(s, in, x, v, node[b], delta + 2 * b, speed[b], n_grasp[b], static_cast<T*>(nullptr),
                            static_cast<T*>(nullptr), out_settled + b, out_diverged + b, w,
                            static_cast<T*>(nullptr), frames ? frames + b * in.frame_cap * 2 * n : nullptr,
                            n_pegs > 0 ? pegs + 3 * n_pegs * b : nullptr, n_pegs, pin ? pin[b] : int64_t(-1));
  });
}

template <typename T>
void backward(const double* fp, const int64_t* ip, const T* pos, const T* vel, const int64_t* node, const T* delta,
              const T* speed, const int64_t* n_grasp, const double* phys, const T* pegs, int64_t n_pegs,
              const int64_t* pin, const T* grad_out_pos, const T* grad_out_vel, const T* grad_frames, T* grad_pos,
              T* grad_vel, T* grad_delta, T* grad_phys) {
  if (!pegs) n_pegs = 0;
  const Scalars s0{fp[0], fp[1], fp[2], fp[3], fp[4], fp[5], fp[6], fp[7], fp[8], fp[9], fp[10], fp[11]};
  const Ints in{ip[0], ip[1], ip[2], ip[3], ip[4], ip[5], ip[6], ip[7], ip[8], ip[9]};
  const int64_t n = in.n;
  const int64_t max_steps = in.fixed_steps >= 0 ? in.fixed_steps : in.max_drag + in.max_settle + 1;
  const int64_t groups = in.use_groups ? in.B / W : 0, first = groups * W;
  parallel_for(groups + in.B - first, in.threads, [&](int64_t task) {
    if (task < groups) {
      backward_group(s0, in, task * W, pos, vel, node, delta, speed, n_grasp, phys, pegs, n_pegs, pin, grad_out_pos,
                     grad_out_vel, grad_frames, grad_pos, grad_vel, grad_delta, grad_phys);
      return;
    }
    const int64_t b = first + task - groups;
    const Scalars s = rope_scalars(s0, phys, b);
    Work<T> w(n);
    // uninitialised: every slot read is written by the recomputation first
    std::unique_ptr<T[]> traj(new T[2 * n * (max_steps + 2)]), betas(new T[(n - 2) * (max_steps + 1)]);
    std::unique_ptr<T[]> vtraj(grad_phys ? new T[2 * n * (max_steps + 2)] : nullptr);
    std::vector<T> x(2 * n), v(2 * n), hu(2 * n);
    std::copy(pos + 2 * n * b, pos + 2 * n * (b + 1), x.begin());
    if (vel) std::copy(vel + 2 * n * b, vel + 2 * n * (b + 1), v.begin());
    else std::fill(v.begin(), v.end(), T(0));
    const int64_t g = node[b];
    const T* d = delta + 2 * b;
    const T sp = speed[b];
    int64_t settled, diverged;
    const T* rope_pegs = n_pegs > 0 ? pegs + 3 * n_pegs * b : nullptr;
    const int64_t pn = pin ? pin[b] : -1;
    const int64_t K = run_rope(s, in, x.data(), v.data(), g, d, sp, n_grasp[b], traj.get(), betas.get(), &settled,
                               &diverged, w, vtraj.get(), static_cast<T*>(nullptr), rope_pegs, n_pegs, pn);

    T* gx = grad_pos + 2 * n * b;
    T* gv = grad_vel + 2 * n * b;
    std::copy(grad_out_pos + 2 * n * b, grad_out_pos + 2 * n * (b + 1), gx);
    if (grad_out_vel) std::copy(grad_out_vel + 2 * n * b, grad_out_vel + 2 * n * (b + 1), gv);
    else std::fill(gv, gv + 2 * n, T(0));
    const T* gf = grad_frames ? grad_frames + b * in.frame_cap * 2 * n : nullptr;
    T gd[2] = {0, 0}, gstart[2] = {0, 0}, gpin[2] = {0, 0};
    T dots[3] = {0, 0, 0}, acc_s = 0, acc_b = 0, acc_c = 0, acc_w = 0;
    const T h = T(s.h), vmax = T(s.vmax);
    const T coef = h * s.inv_m * s.damp;
    // the release (see run_rope): x_out = x_prev + phi (x_K - x_prev) for a rope stopped by the cap
    const T phi = w.phi;
    std::vector<T> gsum(grad_out_pos + 2 * n * b, grad_out_pos + 2 * n * (b + 1));
    const bool frame_at_end = gf && K % in.record_every == 0;     // that frame is x_out too
    if (w.lerped && frame_at_end)
      for (int64_t i = 0; i < 2 * n; ++i) gsum[i] += gf[2 * n * (K / in.record_every) + i];
    const T* gpo = gsum.data();
    const T* gvo = grad_out_vel ? grad_out_vel + 2 * n * b : nullptr;
    T gphi = 0;
    if (w.lerped) {
      std::copy(gsum.begin(), gsum.end(), gx);
      for (int64_t i = 0; i < 2 * n; ++i) {
        gphi += gpo[i] * (w.xcap[i] - w.xprev[i]) + (gvo ? gvo[i] * (w.vcap[i] - w.vprev[i]) : T(0));
        gx[i] *= phi;
        gv[i] *= phi;
      }
    }
    for (int64_t k = K; k >= 1; --k) {
      if (gf && k % in.record_every == 0 && !(w.lerped && k == K)) {
        const T* f = gf + 2 * n * (k / in.record_every);
        for (int64_t i = 0; i < 2 * n; ++i) gx[i] += f[i];
      }
      if (k <= n_grasp[b]) {
        if (pn >= 0) {           // pinned node = start (velocity 0), or free + phi (start - free) on release
          T* a = gx + 2 * pn;
          T* c = gv + 2 * pn;
          if (k == n_grasp[b] && phi < T(1)) {
            const T* ps = pos + 2 * n * b + 2 * pn;
            const T* f = w.pfree;
            gphi += a[0] * (ps[0] - f[0]) + a[1] * (ps[1] - f[1]) + c[0] * (T(0) - f[2]) + c[1] * (T(0) - f[3]);
            gpin[0] += phi * a[0];
            gpin[1] += phi * a[1];
            a[0] *= T(1) - phi, a[1] *= T(1) - phi, c[0] *= T(1) - phi, c[1] *= T(1) - phi;
          } else {
            gpin[0] += a[0];
            gpin[1] += a[1];
            a[0] = a[1] = c[0] = c[1] = T(0);
          }
        }
        T* a = gx + 2 * g;
        T* c = gv + 2 * g;
        if (k == n_grasp[b] && phi < T(1)) {       // node = free + phi (reference - free)
          T start[2] = {pos[2 * n * b + 2 * g], pos[2 * n * b + 2 * g + 1]}, ref[2], refv[2];
          reference(start, d, sp, k, h, ref, refv);
          const T* f = w.free;
          gphi += a[0] * (ref[0] - f[0]) + a[1] * (ref[1] - f[1]) + c[0] * (refv[0] - f[2]) + c[1] * (refv[1] - f[3]);
          T pa[2] = {phi * a[0], phi * a[1]}, pc[2] = {phi * c[0], phi * c[1]};
          reference_adjoint(d, sp, k, h, vmax, pa, pc, gd, gstart);
          a[0] *= T(1) - phi, a[1] *= T(1) - phi, c[0] *= T(1) - phi, c[1] *= T(1) - phi;
        } else {
          reference_adjoint(d, sp, k, h, vmax, a, c, gd, gstart);
          a[0] = a[1] = c[0] = c[1] = T(0);
        }
      }
      // x_k = x_{k-1} + h v_k, v_k = damp (v_{k-1} + h/m F(x_{k-1})), F = -grad E
      for (int64_t i = 0; i < 2 * n; ++i) v[i] = gv[i] + h * gx[i];      // v reused as u
      hvp(s, n, traj.get() + 2 * n * (k - 1), v.data(), hu.data(), w, betas.get() + (n - 2) * (k - 1),
          grad_phys ? dots : static_cast<T*>(nullptr));
      if (n_pegs > 0) {
        const T* xk = traj.get() + 2 * n * (k - 1);
        peg_list_update(s, n, xk, rope_pegs, n_pegs, w.pegs);
        dots[2] = contact_hvp<1>(s, xk, rope_pegs, w.pegs.pairs, k <= n_grasp[b] ? g : int64_t(-1), v.data(),
                                 hu.data());
      }
      if (grad_phys) {     // see backward_group
        const T* vk = vtraj.get() + 2 * n * (k - 1);
        T uv = 0;
        for (int64_t i = 0; i < 2 * n; ++i) uv += v[i] * vk[i];
        acc_s += dots[0];
        acc_b += dots[1];
        if (n_pegs > 0) {
          acc_c += dots[2];
          acc_w += uv + h * T(s.inv_m) * (T(s.ks) * dots[0] + T(s.kb) * dots[1] + dots[2]);
        } else {
          acc_w += uv + h * T(s.inv_m) * (T(s.ks) * dots[0] + T(s.kb) * dots[1]);
        }
      }
      for (int64_t i = 0; i < 2 * n; ++i) {
        gx[i] -= coef * hu[i];
        gv[i] = T(s.damp) * v[i];
      }
      if (w.lerped && k == K) {
        for (int64_t i = 0; i < 2 * n; ++i) {
          gx[i] += (T(1) - phi) * gpo[i];
          if (gvo) gv[i] += (T(1) - phi) * gvo[i];
        }
      }
    }
    if (gf)
      for (int64_t i = 0; i < 2 * n; ++i) gx[i] += gf[i];
    if (n_grasp[b] > 0) {
      gx[2 * g] += gstart[0];
      gx[2 * g + 1] += gstart[1];
      if (pn >= 0) {
        gx[2 * pn] += gpin[0];
        gx[2 * pn + 1] += gpin[1];
      }
    }
    grad_delta[2 * b] = gd[0] + gphi * w.dphi[0];
    grad_delta[2 * b + 1] = gd[1] + gphi * w.dphi[1];
    if (grad_phys) {
      T* gp = grad_phys + 4 * b;
      gp[0] = coef * acc_s;
      gp[1] = coef * acc_b;
      gp[2] = n_pegs > 0 ? h * T(s.damp) * (T(s.ks) * acc_s + T(s.kb) * acc_b + acc_c)
                         : h * T(s.damp) * (T(s.ks) * acc_s + T(s.kb) * acc_b);
      gp[3] = acc_w;
    }
  });
}

// The deepest overlap of each rope's links with its pegs (the Simulator's check of a start state, without torch's
// per-op overhead): out[b] = max over links k and pegs j of R_j + rr - |q - c_j| (peg_closest), pegs per rope.
template <typename T>
void deepest_overlap(int64_t B, int64_t n, const T* pos, const T* pegs, int64_t K, T rr, T* out) {
  for (int64_t b = 0; b < B; ++b) {
    const T* x = pos + 2 * n * b;
    const T* pg = pegs + 3 * K * b;
    T deepest = -std::numeric_limits<T>::infinity();
    for (int64_t k = 0; k + 1 < n; ++k) {
      const T ax = x[2 * k], ay = x[2 * k + 1], ex = x[2 * k + 2] - ax, ey = x[2 * k + 3] - ay;
      for (int64_t j = 0; j < K; ++j) {
        T sv, t, rx, ry, d, z;
        peg_closest(ax, ay, ex, ey, pg[3 * j], pg[3 * j + 1], pg[3 * j + 2] + rr, sv, t, rx, ry, d, z);
        deepest = std::max(deepest, z);
      }
    }
    out[b] = deepest;
  }
}

}  // namespace

extern "C" {
int64_t diffdlo_lanes() { return W; }
#define DIFFDLO_EXPORT(T, SUFFIX)                                                                                  \
  void diffdlo_forward_##SUFFIX(const double* fp, const int64_t* ip, const T* pos, const T* vel,                   \
                                const int64_t* node, const T* delta, const T* speed, const int64_t* n_grasp,       \
                                const double* phys, const T* pegs, int64_t n_pegs, const int64_t* pin,             \
                                T* out_pos, T* out_vel, int64_t* steps, int64_t* settled, int64_t* diverged,       \
                                T* frames) {                                                                       \
    forward<T>(fp, ip, pos, vel, node, delta, speed, n_grasp, phys, pegs, n_pegs, pin, out_pos, out_vel, steps,    \
               settled, diverged, frames);                                                                         \
  }                                                                                                                \
  void diffdlo_backward_##SUFFIX(const double* fp, const int64_t* ip, const T* pos, const T* vel,                  \
                                 const int64_t* node, const T* delta, const T* speed, const int64_t* n_grasp,      \
                                 const double* phys, const T* pegs, int64_t n_pegs, const int64_t* pin,            \
                                 const T* gpos_out, const T* gvel_out, const T* gframes, T* gpos, T* gvel,         \
                                 T* gdelta, T* gphys) {                                                            \
    backward<T>(fp, ip, pos, vel, node, delta, speed, n_grasp, phys, pegs, n_pegs, pin, gpos_out, gvel_out,        \
                gframes, gpos, gvel, gdelta, gphys);                                                               \
  }                                                                                                                \
  /* the deepest overlap z = R + rr - d of any link of each rope (B x n x 2) with its n_pegs pegs, into out[B] */ \
  void diffdlo_overlap_##SUFFIX(int64_t B, int64_t n, const T* pos, const T* pegs, int64_t n_pegs, double rr,       \
                                T* out) {                                                                          \
    deepest_overlap<T>(B, n, pos, pegs, n_pegs, T(rr), out);                                                       \
  }                                                                                                                \
  /* H u of the energy of one rope (n x 2) at x, with n_pegs pegs (x, y, R) and the links at node lift lifted */  \
  void diffdlo_hvp_##SUFFIX(const double* fp, int64_t n, const T* x, const T* u, T* out, const T* pegs,            \
                            int64_t n_pegs, int64_t lift) {                                                        \
    const Scalars s{fp[0], fp[1], fp[2], fp[3], fp[4], fp[5], fp[6], fp[7], fp[8], fp[9], fp[10], fp[11]};         \
    Work<T> w(n);                                                                                                  \
    hvp(s, n, x, u, out, w);                                                                                       \
    if (pegs && n_pegs > 0) {                                                                                      \
      peg_list_update(s, n, x, pegs, n_pegs, w.pegs);                                                              \
      contact_hvp<1>(s, x, pegs, w.pegs.pairs, lift, u, out);                                                      \
    }                                                                                                              \
  }
DIFFDLO_EXPORT(float, f32)
DIFFDLO_EXPORT(double, f64)
}
