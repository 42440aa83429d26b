// Relative node motions as unit dual quaternions on the CPU, forward and hand-written backward.
//
// The formula is worldtree.motion.skinning._relative_dual_tensor: for entry u with node poses (q_t, p_t) at the
// target frame and (q_r, p_r) at a reference frame (quaternions of any norm, normalised here):
//   a = q_t / |q_t|,  b = q_r / |q_r|  (the identity where |q|^2 <= eps^2, as quaternion.normalize),  c = conj(b)
//   q_rel = a c,  t_rel = R(a) (-R(c) p_r) + p_t          (se3.relative: T(t) T(ref)^-1)
//   real = q_rel / |q_rel|,  dual = 0.5 (0, t_rel) real     (dualquat.from_quat_trans)
// The tensor version normalises the unit quaternions again inside rotate and compose; a normalisation of a unit
// vector is the identity and its Jacobian the projector (I - x x^T), which the outer normalisation applies anyway,
// so one normalisation of each input is the same function with the same gradient (up to rounding).
//
// Why a kernel: a photometric step of the scaffold methods builds this table for every (frame, node) pair (40 x
// 500 on the demo) once or twice per step; written with tensors it is about a hundred passes over the table
// forward and backward and cost more than the skinning itself. Here each entry is read once.
//
// Precision: every value and gradient is computed in double and rounded once to float32.
//
// Same results for any thread count: every output is per entry (the sums over entries that share a broadcast
// input are torch's expand backward).

#include <ATen/core/Tensor.h>
#include <ATen/ops/empty.h>
#include <c10/util/Exception.h>
#include <torch/library.h>

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <vector>

#include <omp.h>

#include "quat_cpu.h"

namespace {

using namespace motion_quat;

// v + 2 w (u x v) + 2 u x (u x v) for a unit quaternion (w, u).
inline Vec rel_rotate(const Quat& q, const Vec& v) {
  const Vec u = vec(q);
  const Vec t = cross(u, v);
  const Vec t2 = {2 * t.x, 2 * t.y, 2 * t.z};
  const Vec ut = cross(u, t2);
  return {v.x + q.w * t2.x + ut.x, v.y + q.w * t2.y + ut.y, v.z + q.w * t2.z + ut.z};
}

// Gradient of g . R(q) v with respect to the unit quaternion q = (w, u), as if its four components were free:
// d/dw = 2 g.(u x v), d/du = 2 w (v x g) + 2 ((u.v) g + (u.g) v - 2 (g.v) u).
inline Quat rel_rotate_grad_q(const Quat& q, const Vec& v, const Vec& g) {
  const Vec u = vec(q);
  const Vec uv = cross(u, v), vg = cross(v, g);
  const double u_v = dot(u, v), u_g = dot(u, g), g_v = dot(g, v);
  return {2 * dot(g, uv), 2 * (q.w * vg.x + u_v * g.x + u_g * v.x - 2 * g_v * u.x),
          2 * (q.w * vg.y + u_v * g.y + u_g * v.y - 2 * g_v * u.y),
          2 * (q.w * vg.z + u_v * g.z + u_g * v.z - 2 * g_v * u.z)};
}

struct Entry {
  Quat a, c, real;
  Vec ti, trel;
  double inv_a, inv_b, inv_rel;
};

inline Entry rel_forward_one(const float* qt, const float* pt, const float* qr, const float* pr, double eps2) {
  Entry e;
  e.a = unit(load(qt), eps2, &e.inv_a);
  const Quat b = unit(load(qr), eps2, &e.inv_b);
  e.c = conj(b);
  const Vec rp = rel_rotate(e.c, {pr[0], pr[1], pr[2]});
  e.ti = {-rp.x, -rp.y, -rp.z};
  const Vec ra = rel_rotate(e.a, e.ti);
  e.trel = {ra.x + pt[0], ra.y + pt[1], ra.z + pt[2]};
  // The guard cannot trigger for unit a and c; it is the tensor version's (from_quat_trans normalises again).
  e.real = unit(mul(e.a, e.c), eps2, &e.inv_rel);
  return e;
}

void rel_check(const at::Tensor& t, int64_t U, int64_t C, const char* what) {
  TORCH_CHECK(t.dim() == 2 && t.size(0) == U && t.size(1) == C && t.scalar_type() == at::kFloat &&
                  t.is_contiguous() && t.device().is_cpu(),
              "relative_dual: ", what, " must be a contiguous float32 CPU [U, ", C, "] tensor");
}

}  // namespace

// (real [U, 4], dual [U, 4]) float32 of T(q_t, p_t) T(q_r, p_r)^-1 for every entry.
std::vector<at::Tensor> relative_dual_forward(at::Tensor q_t, at::Tensor p_t, at::Tensor q_r, at::Tensor p_r,
                                              double eps, int64_t threads) {
  const int64_t U = q_t.size(0);
  rel_check(q_t, U, 4, "q_t");
  rel_check(p_t, U, 3, "p_t");
  rel_check(q_r, U, 4, "q_ref");
  rel_check(p_r, U, 3, "p_ref");
  auto real = at::empty({U, 4}, q_t.options());
  auto dual = at::empty({U, 4}, q_t.options());
  const float *qt = q_t.data_ptr<float>(), *pt = p_t.data_ptr<float>(), *qr = q_r.data_ptr<float>(),
              *pr = p_r.data_ptr<float>();
  float *ore = real.data_ptr<float>(), *odu = dual.data_ptr<float>();
  const double eps2 = eps * eps;
#pragma omp parallel for schedule(static) num_threads(int(std::max<int64_t>(threads, 1)))
  for (int64_t u = 0; u < U; ++u) {
    const Entry e = rel_forward_one(qt + 4 * u, pt + 3 * u, qr + 4 * u, pr + 3 * u, eps2);
    const Quat& r = e.real;
    const Vec& t = e.trel;
    // dual = 0.5 (0, t) r = 0.5 (-t.rv, rw t + t x rv)
    const Vec rv = vec(r);
    const Vec txr = cross(t, rv);
    float* o = ore + 4 * u;
    o[0] = float(r.w), o[1] = float(r.x), o[2] = float(r.y), o[3] = float(r.z);
    float* d = odu + 4 * u;
    d[0] = float(-0.5 * dot(t, rv));
    d[1] = float(0.5 * (r.w * t.x + txr.x));
    d[2] = float(0.5 * (r.w * t.y + txr.y));
    d[3] = float(0.5 * (r.w * t.z + txr.z));
  }
  return {real, dual};
}

// Gradients (q_t [U, 4], p_t [U, 3], q_ref [U, 4], p_ref [U, 3]) for upstream gradients g_real, g_dual [U, 4].
std::vector<at::Tensor> relative_dual_backward(at::Tensor q_t, at::Tensor p_t, at::Tensor q_r, at::Tensor p_r,
                                               at::Tensor g_real, at::Tensor g_dual, double eps, int64_t threads) {
  const int64_t U = q_t.size(0);
  rel_check(q_t, U, 4, "q_t");
  rel_check(p_t, U, 3, "p_t");
  rel_check(q_r, U, 4, "q_ref");
  rel_check(p_r, U, 3, "p_ref");
  rel_check(g_real, U, 4, "g_real");
  rel_check(g_dual, U, 4, "g_dual");
  auto gqt = at::empty({U, 4}, q_t.options()), gpt = at::empty({U, 3}, q_t.options()),
       gqr = at::empty({U, 4}, q_t.options()), gpr = at::empty({U, 3}, q_t.options());
  const float *qt = q_t.data_ptr<float>(), *pt = p_t.data_ptr<float>(), *qr = q_r.data_ptr<float>(),
              *pr = p_r.data_ptr<float>(), *gre = g_real.data_ptr<float>(), *gdu = g_dual.data_ptr<float>();
  float *oqt = gqt.data_ptr<float>(), *opt = gpt.data_ptr<float>(), *oqr = gqr.data_ptr<float>(),
        *opr = gpr.data_ptr<float>();
  const double eps2 = eps * eps;
#pragma omp parallel for schedule(static) num_threads(int(std::max<int64_t>(threads, 1)))
  for (int64_t u = 0; u < U; ++u) {
    const Entry e = rel_forward_one(qt + 4 * u, pt + 3 * u, qr + 4 * u, pr + 3 * u, eps2);
    const Quat& r = e.real;
    const Vec rv = vec(r), t = e.trel;
    const float* G = gre + 4 * u;
    const float* D = gdu + 4 * u;
    const double Gdw = D[0];
    const Vec Gdv = {D[1], D[2], D[3]};
    // dual = 0.5 (-t.rv, rw t + t x rv): into t and into real
    const Vec rxg = cross(rv, Gdv);
    const Vec g_t = {0.5 * (-Gdw * rv.x + r.w * Gdv.x + rxg.x), 0.5 * (-Gdw * rv.y + r.w * Gdv.y + rxg.y),
                     0.5 * (-Gdw * rv.z + r.w * Gdv.z + rxg.z)};
    const Vec gxt = cross(Gdv, t);
    const Quat g_real_all = {G[0] + 0.5 * dot(t, Gdv), G[1] + 0.5 * (-Gdw * t.x + gxt.x),
                             G[2] + 0.5 * (-Gdw * t.y + gxt.y), G[3] + 0.5 * (-Gdw * t.z + gxt.z)};
    // real = q_rel / |q_rel|; q_rel = a c
    const Quat g_qrel = unit_grad(r, g_real_all, e.inv_rel);
    Quat g_a = mul(g_qrel, conj(e.c));
    Quat g_c = mul(conj(e.a), g_qrel);
    // t_rel = R(a) ti + p_t
    const Quat ga_rot = rel_rotate_grad_q(e.a, e.ti, g_t);
    g_a = {g_a.w + ga_rot.w, g_a.x + ga_rot.x, g_a.y + ga_rot.y, g_a.z + ga_rot.z};
    const Vec g_ti = rel_rotate(conj(e.a), g_t);  // R(a)^T g_t
    // ti = -R(c) p_r
    const Vec p = {pr[3 * u], pr[3 * u + 1], pr[3 * u + 2]};
    const Vec m_gti = {-g_ti.x, -g_ti.y, -g_ti.z};
    const Vec g_p = rel_rotate(conj(e.c), m_gti);  // R(c)^T (-g_ti)
    const Quat gc_rot = rel_rotate_grad_q(e.c, p, m_gti);
    g_c = {g_c.w + gc_rot.w, g_c.x + gc_rot.x, g_c.y + gc_rot.y, g_c.z + gc_rot.z};
    // c = conj(b); a, b = normalised inputs
    const Quat g_b = conj(g_c);
    const Quat gq_t = unit_grad(e.a, g_a, e.inv_a);
    const Quat gq_r = unit_grad(conj(e.c), g_b, e.inv_b);
    float* o = oqt + 4 * u;
    o[0] = float(gq_t.w), o[1] = float(gq_t.x), o[2] = float(gq_t.y), o[3] = float(gq_t.z);
    o = oqr + 4 * u;
    o[0] = float(gq_r.w), o[1] = float(gq_r.x), o[2] = float(gq_r.y), o[3] = float(gq_r.z);
    o = opt + 3 * u;
    o[0] = float(g_t.x), o[1] = float(g_t.y), o[2] = float(g_t.z);
    o = opr + 3 * u;
    o[0] = float(g_p.x), o[1] = float(g_p.y), o[2] = float(g_p.z);
  }
  return {gqt, gpt, gqr, gpr};
}

// Joins the rasterizer's op namespace (the build's name; see the end of rasterize_cpu.cpp for the macro level).
#define WORLDTREE_LIBRARY_FRAGMENT(ns, m) TORCH_LIBRARY_FRAGMENT(ns, m)
WORLDTREE_LIBRARY_FRAGMENT(TORCH_EXTENSION_NAME, m) {
  m.def("relative_dual_forward", &relative_dual_forward);    // node motions as dual quaternions (CPU, float32)
  m.def("relative_dual_backward", &relative_dual_backward);  // their gradients
}
