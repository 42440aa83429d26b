// The motion scaffold's velocity and acceleration terms on the CPU, forward and hand-written backward.
//
// The formulas are worldtree.motion.regularizers.velocity_losses and acceleration_losses, guards included: over
// node trajectories pos [T, M, 3] and quat [T, M, 4] (any norm; qn = q / |q|, the identity where |q|^2 <= eps^2),
//   v_xyz = mean |x(t+1) - x(t)|               v_rot = mean angle(qn(t), qn(t+1))
//   a_xyz = mean |x(t+2) - 2 x(t+1) + x(t)|    a_rot = mean angle(d(t), d(t+1)),  d(t) = qn(t+1) conj(qn(t))
// with |v| = sqrt(max(|v|^2, FLT_MIN)) (safe_norm) and angle(a, b) = 2 atan2(|r_v|, |r_w|) of r = conj(a) b,
// |r_v| guarded the same way (quaternion.angle_between_components). The means are over (T - 1) M and (T - 2) M
// entries (0 with none). The gradients of clamp, abs and atan2 are torch's.
//
// Why a kernel: written with tensors these four terms are some two hundred passes over the scaffold's [T, M]
// tables per photometric step (forward and backward), as much as the ARAP terms. Here each node's trajectory is
// read once.
//
// Precision and threads: computed in double and rounded once. Nodes are split between threads; each node's sums
// are kept apart and added in node order afterwards, and every gradient belongs to one node, so the results are
// the same for any thread count.

#include <ATen/core/Tensor.h>
#include <ATen/ops/empty.h>
#include <ATen/ops/zeros.h>
#include <c10/util/Exception.h>
#include <torch/library.h>

#include <algorithm>
#include <cfloat>
#include <cmath>
#include <cstdint>
#include <vector>

#include <omp.h>

#include "quat_cpu.h"

namespace {

using namespace motion_quat;

constexpr double kTiny = FLT_MIN;  // torch.finfo(float32).tiny: the float32 tensor version's clamp

// r = conj(a) b written out as angle_between_components does: r_w = a.b, r_v = a_w b_v - b_w a_v - a_v x b_v.
struct AngleParts {
  double rw, rx, ry, rz, sq, s;
};
inline AngleParts sm_angle_parts(const Quat& a, const Quat& b) {
  AngleParts p;
  p.rw = a.w * b.w + a.x * b.x + a.y * b.y + a.z * b.z;
  p.rx = a.w * b.x - b.w * a.x - (a.y * b.z - a.z * b.y);
  p.ry = a.w * b.y - b.w * a.y - (a.z * b.x - a.x * b.z);
  p.rz = a.w * b.z - b.w * a.z - (a.x * b.y - a.y * b.x);
  p.sq = p.rx * p.rx + p.ry * p.ry + p.rz * p.rz;
  p.s = std::sqrt(std::max(p.sq, kTiny));
  return p;
}
inline double sm_angle(const Quat& a, const Quat& b) {
  const AngleParts p = sm_angle_parts(a, b);
  return 2.0 * std::atan2(p.s, std::fabs(p.rw));
}

// Adds w * d angle(a, b) / d(a, b) to ga, gb.
inline void sm_angle_grad(const Quat& a, const Quat& b, double w, Quat& ga, Quat& gb) {
  const AngleParts p = sm_angle_parts(a, b);
  const double c = std::fabs(p.rw), den = p.s * p.s + c * c;
  const double d_s = 2.0 * c / den * w, d_c = -2.0 * p.s / den * w;
  const double g_rw = p.rw > 0 ? d_c : (p.rw < 0 ? -d_c : 0.0);
  const double k = p.sq >= kTiny ? d_s * 0.5 / p.s * 2.0 : 0.0;  // through sqrt(clamp(sq)) then sq = |r_v|^2
  const double gx = k * p.rx, gy = k * p.ry, gz = k * p.rz;
  // r_w = a.b
  ga.w += g_rw * b.w, ga.x += g_rw * b.x, ga.y += g_rw * b.y, ga.z += g_rw * b.z;
  gb.w += g_rw * a.w, gb.x += g_rw * a.x, gb.y += g_rw * a.y, gb.z += g_rw * a.z;
  // r_v = a_w b_v - b_w a_v - a_v x b_v: d/da_v (a_v x b_v).g = b_v x g, d/db_v = g x a_v
  ga.w += gx * b.x + gy * b.y + gz * b.z;
  gb.w -= gx * a.x + gy * a.y + gz * a.z;
  ga.x += -b.w * gx - (b.y * gz - b.z * gy);
  ga.y += -b.w * gy - (b.z * gx - b.x * gz);
  ga.z += -b.w * gz - (b.x * gy - b.y * gx);
  gb.x += a.w * gx - (gy * a.z - gz * a.y);
  gb.y += a.w * gy - (gz * a.x - gx * a.z);
  gb.z += a.w * gz - (gx * a.y - gy * a.x);
}

inline double sm_norm3(double x, double y, double z, double* sq) {
  *sq = x * x + y * y + z * z;
  return std::sqrt(std::max(*sq, kTiny));
}

struct SmoothIn {
  const float* pos;   // [T, M, 3]
  const float* quat;  // [T, M, 4]
  int64_t T, M;
  double eps2;
};

// The unit quaternions of node m at every frame (and 1 / |q|, 0 for the identity fallback).
inline void sm_units(const SmoothIn& in, int64_t m, std::vector<Quat>& qn, std::vector<double>& inv) {
  for (int64_t t = 0; t < in.T; ++t) qn[t] = unit(load(in.quat + 4 * (t * in.M + m)), in.eps2, &inv[t]);
}

inline const float* sm_p(const SmoothIn& in, int64_t t, int64_t m) { return in.pos + 3 * (t * in.M + m); }

SmoothIn sm_inputs(const at::Tensor& pos, const at::Tensor& quat, double eps) {
  TORCH_CHECK(pos.dim() == 3 && pos.size(2) == 3 && pos.scalar_type() == at::kFloat && pos.is_contiguous() &&
                  pos.device().is_cpu(),
              "motion_smooth: pos must be a contiguous float32 CPU [T, M, 3] tensor");
  TORCH_CHECK(quat.dim() == 3 && quat.size(0) == pos.size(0) && quat.size(1) == pos.size(1) && quat.size(2) == 4 &&
                  quat.scalar_type() == at::kFloat && quat.is_contiguous() && quat.device().is_cpu(),
              "motion_smooth: quat must be a contiguous float32 CPU [T, M, 4] tensor");
  return SmoothIn{pos.data_ptr<float>(), quat.data_ptr<float>(), pos.size(0), pos.size(1), eps * eps};
}

}  // namespace

// [4] float32: v_xyz, v_rot, a_xyz, a_rot (the means above).
at::Tensor motion_smooth_forward(at::Tensor pos, at::Tensor quat, double eps, int64_t threads) {
  const SmoothIn in = sm_inputs(pos, quat, eps);
  const int64_t T = in.T, M = in.M;
  std::vector<double> part(4 * M, 0.0);
#pragma omp parallel num_threads(int(std::max<int64_t>(threads, 1)))
  {
    std::vector<Quat> qn(T), d(T > 1 ? T - 1 : 0);
    std::vector<double> inv(T);
#pragma omp for schedule(static)
    for (int64_t m = 0; m < M; ++m) {
      sm_units(in, m, qn, inv);
      double vx = 0, vr = 0, ax = 0, ar = 0, sq;
      for (int64_t t = 0; t + 1 < T; ++t) {
        const float *p0 = sm_p(in, t, m), *p1 = sm_p(in, t + 1, m);
        vx += sm_norm3(double(p1[0]) - p0[0], double(p1[1]) - p0[1], double(p1[2]) - p0[2], &sq);
        vr += sm_angle(qn[t], qn[t + 1]);
        d[t] = mul(qn[t + 1], conj(qn[t]));
      }
      for (int64_t t = 0; t + 2 < T; ++t) {
        const float *p0 = sm_p(in, t, m), *p1 = sm_p(in, t + 1, m), *p2 = sm_p(in, t + 2, m);
        ax += sm_norm3(double(p2[0]) - 2.0 * p1[0] + p0[0], double(p2[1]) - 2.0 * p1[1] + p0[1],
                       double(p2[2]) - 2.0 * p1[2] + p0[2], &sq);
        ar += sm_angle(d[t], d[t + 1]);
      }
      part[4 * m] = vx, part[4 * m + 1] = vr, part[4 * m + 2] = ax, part[4 * m + 3] = ar;
    }
  }
  double sum[4] = {0, 0, 0, 0};
  for (int64_t m = 0; m < M; ++m)
    for (int c = 0; c < 4; ++c) sum[c] += part[4 * m + c];
  const double nv = double(std::max<int64_t>((T - 1) * M, 1)), na = double(std::max<int64_t>((T - 2) * M, 1));
  auto out = at::empty({4}, pos.options());
  float* o = out.data_ptr<float>();
  o[0] = float(T >= 2 ? sum[0] / nv : 0.0), o[1] = float(T >= 2 ? sum[1] / nv : 0.0);
  o[2] = float(T >= 3 ? sum[2] / na : 0.0), o[3] = float(T >= 3 ? sum[3] / na : 0.0);
  return out;
}

// Gradients (pos [T, M, 3], quat [T, M, 4]) for the upstream gradient g [4] of the four means.
std::vector<at::Tensor> motion_smooth_backward(at::Tensor pos, at::Tensor quat, at::Tensor g, double eps,
                                               int64_t threads) {
  const SmoothIn in = sm_inputs(pos, quat, eps);
  TORCH_CHECK(g.numel() == 4 && g.scalar_type() == at::kFloat && g.is_contiguous() && g.device().is_cpu(),
              "motion_smooth_backward: g must be a contiguous float32 CPU [4] tensor");
  const int64_t T = in.T, M = in.M;
  auto gpos = at::zeros({T, M, 3}, pos.options()), gquat = at::zeros({T, M, 4}, quat.options());
  float *gp = gpos.data_ptr<float>(), *gq = gquat.data_ptr<float>();
  const float* gi = g.data_ptr<float>();
  const double nv = double(std::max<int64_t>((T - 1) * M, 1)), na = double(std::max<int64_t>((T - 2) * M, 1));
  const double wv = gi[0] / nv, wvr = gi[1] / nv, wa = gi[2] / na, war = gi[3] / na;
#pragma omp parallel num_threads(int(std::max<int64_t>(threads, 1)))
  {
    std::vector<Quat> qn(T), d(T > 1 ? T - 1 : 0), gqn(T), gd(T > 1 ? T - 1 : 0);
    std::vector<double> inv(T), gx(3 * T);
#pragma omp for schedule(static)
    for (int64_t m = 0; m < M; ++m) {
      sm_units(in, m, qn, inv);
      std::fill(gqn.begin(), gqn.end(), Quat{0, 0, 0, 0});
      std::fill(gd.begin(), gd.end(), Quat{0, 0, 0, 0});
      std::fill(gx.begin(), gx.end(), 0.0);
      double sq;
      for (int64_t t = 0; t + 1 < T; ++t) {
        const float *p0 = sm_p(in, t, m), *p1 = sm_p(in, t + 1, m);
        const double dx = double(p1[0]) - p0[0], dy = double(p1[1]) - p0[1], dz = double(p1[2]) - p0[2];
        const double s = sm_norm3(dx, dy, dz, &sq);
        const double k = sq >= kTiny ? wv / s : 0.0;
        gx[3 * (t + 1)] += k * dx, gx[3 * (t + 1) + 1] += k * dy, gx[3 * (t + 1) + 2] += k * dz;
        gx[3 * t] -= k * dx, gx[3 * t + 1] -= k * dy, gx[3 * t + 2] -= k * dz;
        sm_angle_grad(qn[t], qn[t + 1], wvr, gqn[t], gqn[t + 1]);
        d[t] = mul(qn[t + 1], conj(qn[t]));
      }
      for (int64_t t = 0; t + 2 < T; ++t) {
        const float *p0 = sm_p(in, t, m), *p1 = sm_p(in, t + 1, m), *p2 = sm_p(in, t + 2, m);
        const double dx = double(p2[0]) - 2.0 * p1[0] + p0[0], dy = double(p2[1]) - 2.0 * p1[1] + p0[1],
                     dz = double(p2[2]) - 2.0 * p1[2] + p0[2];
        const double s = sm_norm3(dx, dy, dz, &sq);
        const double k = sq >= kTiny ? wa / s : 0.0;
        const double c[3] = {1.0, -2.0, 1.0};
        for (int j = 0; j < 3; ++j) {
          gx[3 * (t + j)] += c[j] * k * dx, gx[3 * (t + j) + 1] += c[j] * k * dy, gx[3 * (t + j) + 2] += c[j] * k * dz;
        }
        sm_angle_grad(d[t], d[t + 1], war, gd[t], gd[t + 1]);
      }
      // d(t) = x y* with x = qn(t+1), y = qn(t): g_x = g_d y, g_y = conj(conj(x) g_d)
      for (int64_t t = 0; t + 1 < T; ++t) {
        const Quat g_x = mul(gd[t], qn[t]);
        const Quat g_y = conj(mul(conj(qn[t + 1]), gd[t]));
        gqn[t + 1].w += g_x.w, gqn[t + 1].x += g_x.x, gqn[t + 1].y += g_x.y, gqn[t + 1].z += g_x.z;
        gqn[t].w += g_y.w, gqn[t].x += g_y.x, gqn[t].y += g_y.y, gqn[t].z += g_y.z;
      }
      for (int64_t t = 0; t < T; ++t) {
        const Quat g_q = unit_grad(qn[t], gqn[t], inv[t]);
        float* o = gq + 4 * (t * M + m);
        o[0] = float(g_q.w), o[1] = float(g_q.x), o[2] = float(g_q.y), o[3] = float(g_q.z);
        float* op = gp + 3 * (t * M + m);
        op[0] = float(gx[3 * t]), op[1] = float(gx[3 * t + 1]), op[2] = float(gx[3 * t + 2]);
      }
    }
  }
  return {gpos, gquat};
}

// Joins the rasterizer's op namespace (the build's name; see the end of rasterize_cpu.cpp for the macro level).
#define WORLDTREE_LIBRARY_FRAGMENT(ns, m) TORCH_LIBRARY_FRAGMENT(ns, m)
WORLDTREE_LIBRARY_FRAGMENT(TORCH_EXTENSION_NAME, m) {
  m.def("motion_smooth_forward", &motion_smooth_forward);    // velocity and acceleration terms (CPU, float32)
  m.def("motion_smooth_backward", &motion_smooth_backward);  // their gradients
}
