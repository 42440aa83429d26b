// As-rigid-as-possible terms of scaffold node trajectories, forward and backward in one pass per edge.
//
// The formula is worldtree.motion.regularizers.arap_loss (docs/motion.md): for node i, neighbour j = idx[i, k]
// with normalised weight w[i, k], local coordinates c(t) = R_j(t)^T (x_i(t) - x_j(t)) and, for each shift s,
//   coord  += ws / ((T - s) M) * sum_t w_ik |c(t) - c(t + s)|
//   length += ws / ((T - s) M) * sum_t w_ik | |c(t)| - |c(t + s)| |
// with norms guarded as there (squared norm clamped at FLT_MIN, gradient 0 below it).
//
// Why a kernel: written with tensors, every term is a dozen passes over [9, M, K, T] temporaries, which made
// the regulariser about a third of a photometric step on a CPU; here each edge's trajectory is read once and
// its values stay in a small per-thread buffer.
//
// Trajectories are node-major ([M, T, 3] positions, [M, T, 9] rotations): one edge reads two nodes' whole
// trajectories as contiguous runs, where the frame-major [T, M, ...] layout would touch a new cache line per
// frame and node (the scaffold has thousands of nodes, so consecutive frames of one node are far apart).
//
// Same results on any machine and thread count: every sum has a fixed order. The loss sums each node's edges
// in double into a per-node slot, then the slots in node order. The backward is two passes: over nodes i (the
// gradient of x_i: its own edges), then over nodes j (the gradient of x_j and R_j: the edges that have j as
// neighbour, in (i, k) order, recomputed), so no two threads write one value and no atomic is needed.

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

namespace {

struct ArapEdgeBuffers {
  std::vector<double> d, c, len, gc, gl;
  std::vector<char> ok;
  explicit ArapEdgeBuffers(int64_t T) : d(3 * T), c(3 * T), len(T), gc(3 * T), gl(T), ok(T) {}
};

struct ArapInputs {
  const float* pos;  // [M, T, 3]
  const float* R;    // [M, T, 9], entry (a, b) at 3a + b
  int64_t T, M;
  std::vector<int64_t> shifts;
  std::vector<double> scales;  // ws / max((T - s) M, 1) per shift, 0 for shifts with T <= s
};

// A squared norm clamped below at FLT_MIN (as torch.clamp: a NaN stays NaN, so a NaN position shows in the loss).
inline double guarded(double sq) { return sq < double(FLT_MIN) ? double(FLT_MIN) : sq; }

// d(t) = x_i(t) - x_j(t), c(t) = R_j(t)^T d(t), |c(t)| guarded.
inline void edge_coordinates(const ArapInputs& in, int64_t i, int64_t j, ArapEdgeBuffers& b) {
  for (int64_t t = 0; t < in.T; ++t) {
    const float* xi = in.pos + (i * in.T + t) * 3;
    const float* xj = in.pos + (j * in.T + t) * 3;
    const float* r = in.R + (j * in.T + t) * 9;
    double d0 = double(xi[0]) - double(xj[0]), d1 = double(xi[1]) - double(xj[1]), d2 = double(xi[2]) - double(xj[2]);
    double* d = &b.d[3 * t];
    double* c = &b.c[3 * t];
    d[0] = d0;
    d[1] = d1;
    d[2] = d2;
    for (int q = 0; q < 3; ++q) c[q] = double(r[q]) * d0 + double(r[3 + q]) * d1 + double(r[6 + q]) * d2;
    double sq = c[0] * c[0] + c[1] * c[1] + c[2] * c[2];
    b.ok[t] = sq >= double(FLT_MIN);
    b.len[t] = std::sqrt(guarded(sq));
  }
}

// Both loss terms of one edge (weight w), not yet scaled by the edge weight.
inline void edge_losses(const ArapInputs& in, const ArapEdgeBuffers& b, double& coord, double& length) {
  for (size_t n = 0; n < in.shifts.size(); ++n) {
    const int64_t s = in.shifts[n];
    if (in.T <= s) continue;
    double sc = 0.0, sl = 0.0;
    for (int64_t t = 0; t + s < in.T; ++t) {
      const double* a = &b.c[3 * t];
      const double* z = &b.c[3 * (t + s)];
      double e0 = a[0] - z[0], e1 = a[1] - z[1], e2 = a[2] - z[2];
      double sq = e0 * e0 + e1 * e1 + e2 * e2;
      sc += std::sqrt(guarded(sq));
      sl += std::fabs(b.len[t] - b.len[t + s]);
    }
    coord += in.scales[n] * sc;
    length += in.scales[n] * sl;
  }
}

// g_c(t) = d loss / d c(t) of one edge with weight w (the upstream gradients folded in).
inline void edge_grad_c(const ArapInputs& in, ArapEdgeBuffers& b, double w, double g_coord, double g_len) {
  std::fill(b.gc.begin(), b.gc.end(), 0.0);
  std::fill(b.gl.begin(), b.gl.end(), 0.0);
  for (size_t n = 0; n < in.shifts.size(); ++n) {
    const int64_t s = in.shifts[n];
    if (in.T <= s) continue;
    const double kc = g_coord * in.scales[n] * w, kl = g_len * in.scales[n] * w;
    for (int64_t t = 0; t + s < in.T; ++t) {
      const double* a = &b.c[3 * t];
      const double* z = &b.c[3 * (t + s)];
      double e0 = a[0] - z[0], e1 = a[1] - z[1], e2 = a[2] - z[2];
      double sq = e0 * e0 + e1 * e1 + e2 * e2;
      if (sq >= double(FLT_MIN)) {
        double f = kc / std::sqrt(sq);
        b.gc[3 * t] += f * e0;
        b.gc[3 * t + 1] += f * e1;
        b.gc[3 * t + 2] += f * e2;
        b.gc[3 * (t + s)] -= f * e0;
        b.gc[3 * (t + s) + 1] -= f * e1;
        b.gc[3 * (t + s) + 2] -= f * e2;
      }
      double dl = b.len[t] - b.len[t + s];
      double v = dl > 0 ? kl : (dl < 0 ? -kl : 0.0);
      b.gl[t] += v;
      b.gl[t + s] -= v;
    }
  }
  for (int64_t t = 0; t < in.T; ++t) {
    if (!b.ok[t]) continue;
    double f = b.gl[t] / b.len[t];
    for (int q = 0; q < 3; ++q) b.gc[3 * t + q] += f * b.c[3 * t + q];
  }
}

ArapInputs arap_inputs(const at::Tensor& pos, const at::Tensor& R, const at::Tensor& idx, const at::Tensor& w,
                       const std::vector<int64_t>& shifts, const std::vector<double>& shift_weights) {
  TORCH_CHECK(pos.dim() == 3 && pos.size(2) == 3 && pos.is_contiguous() && pos.scalar_type() == at::kFloat,
              "arap: pos must be a contiguous float32 [M, T, 3] tensor");
  const int64_t M = pos.size(0), T = pos.size(1);
  TORCH_CHECK(R.dim() == 3 && R.size(0) == M && R.size(1) == T && R.size(2) == 9 && R.is_contiguous() &&
                  R.scalar_type() == at::kFloat,
              "arap: R must be a contiguous float32 [M, T, 9] tensor");
  TORCH_CHECK(idx.dim() == 2 && idx.size(0) == M && idx.is_contiguous() && idx.scalar_type() == at::kLong,
              "arap: idx must be a contiguous int64 [M, K] tensor");
  TORCH_CHECK(w.sizes() == idx.sizes() && w.is_contiguous() && w.scalar_type() == at::kFloat,
              "arap: w must be a contiguous float32 [M, K] tensor");
  TORCH_CHECK(shifts.size() == shift_weights.size(), "arap: shifts and shift_weights need equal lengths");
  const int64_t* ix = idx.data_ptr<int64_t>();
  for (int64_t n = 0; n < idx.numel(); ++n) TORCH_CHECK(ix[n] >= 0 && ix[n] < M, "arap: idx out of range");
  ArapInputs in{pos.data_ptr<float>(), R.data_ptr<float>(), T, M, shifts, {}};
  for (size_t n = 0; n < shifts.size(); ++n) {
    TORCH_CHECK(shifts[n] >= 1, "arap: shifts must be >= 1");
    const int64_t den = std::max<int64_t>((T - shifts[n]) * M, 1);
    in.scales.push_back(T <= shifts[n] ? 0.0 : shift_weights[n] / double(den));
  }
  return in;
}

}  // namespace

// (coord, length) as two 0-d float32 tensors.
std::vector<at::Tensor> arap_forward(at::Tensor pos, at::Tensor R, at::Tensor idx, at::Tensor w,
                                     std::vector<int64_t> shifts, std::vector<double> shift_weights,
                                     int64_t threads) {
  const ArapInputs in = arap_inputs(pos, R, idx, w, shifts, shift_weights);
  const int64_t M = in.M, K = idx.size(1);
  const int64_t* ix = idx.data_ptr<int64_t>();
  const float* wt = w.data_ptr<float>();
  std::vector<double> node_coord(M, 0.0), node_len(M, 0.0);
#pragma omp parallel num_threads(std::max<int64_t>(threads, 1))
  {
    ArapEdgeBuffers b(in.T);
#pragma omp for schedule(static)
    for (int64_t i = 0; i < M; ++i) {
      double ci = 0.0, li = 0.0;
      for (int64_t k = 0; k < K; ++k) {
        const double we = wt[i * K + k];
        if (we == 0.0) continue;
        double ce = 0.0, le = 0.0;
        edge_coordinates(in, i, ix[i * K + k], b);
        edge_losses(in, b, ce, le);
        ci += we * ce;
        li += we * le;
      }
      node_coord[i] = ci;
      node_len[i] = li;
    }
  }
  double coord = 0.0, length = 0.0;
  for (int64_t i = 0; i < M; ++i) {
    coord += node_coord[i];
    length += node_len[i];
  }
  auto opts = pos.options();
  auto out_c = at::empty({}, opts), out_l = at::empty({}, opts);
  out_c.data_ptr<float>()[0] = float(coord);
  out_l.data_ptr<float>()[0] = float(length);
  return {out_c, out_l};
}

// (g_pos [M, T, 3], g_R [M, T, 9]) for upstream gradients (g_coord, g_length); with detach_neighbours the
// neighbours are constants (x_j and R_j get nothing from the edge) and g_R is all zeros.
std::vector<at::Tensor> arap_backward(at::Tensor pos, at::Tensor R, at::Tensor idx, at::Tensor w,
                                      std::vector<int64_t> shifts, std::vector<double> shift_weights,
                                      double g_coord, double g_length, bool detach_neighbours, int64_t threads) {
  const ArapInputs in = arap_inputs(pos, R, idx, w, shifts, shift_weights);
  const int64_t T = in.T, M = in.M, K = idx.size(1);
  const int64_t* ix = idx.data_ptr<int64_t>();
  const float* wt = w.data_ptr<float>();
  auto g_pos = at::zeros({M, T, 3}, pos.options());
  auto g_R = at::zeros({M, T, 9}, pos.options());
  float* gp = g_pos.data_ptr<float>();
  float* gr = g_R.data_ptr<float>();
  const int nt = int(std::max<int64_t>(threads, 1));

  // Pass 1: x_i's gradient from its own edges, g_x_i(t) = sum_k R_j(t) g_c(t).
#pragma omp parallel num_threads(nt)
  {
    ArapEdgeBuffers b(T);
    std::vector<double> acc(3 * T);
#pragma omp for schedule(static)
    for (int64_t i = 0; i < M; ++i) {
      std::fill(acc.begin(), acc.end(), 0.0);
      for (int64_t k = 0; k < K; ++k) {
        const double we = wt[i * K + k];
        if (we == 0.0) continue;
        const int64_t j = ix[i * K + k];
        edge_coordinates(in, i, j, b);
        edge_grad_c(in, b, we, g_coord, g_length);
        for (int64_t t = 0; t < T; ++t) {
          const float* r = in.R + (j * T + t) * 9;
          const double* g = &b.gc[3 * t];
          for (int a = 0; a < 3; ++a)
            acc[3 * t + a] += double(r[3 * a]) * g[0] + double(r[3 * a + 1]) * g[1] + double(r[3 * a + 2]) * g[2];
        }
      }
      for (int64_t t = 0; t < T; ++t)
        for (int a = 0; a < 3; ++a) gp[(i * T + t) * 3 + a] = float(acc[3 * t + a]);
    }
  }
  if (detach_neighbours) return {g_pos, g_R};

  // Incoming edges of every node, in (i, k) order: a counting sort by neighbour.
  std::vector<int64_t> start(M + 1, 0), edges(M * K);
  for (int64_t e = 0; e < M * K; ++e) start[ix[e] + 1] += 1;
  for (int64_t j = 0; j < M; ++j) start[j + 1] += start[j];
  {
    std::vector<int64_t> fill(start.begin(), start.end() - 1);
    for (int64_t e = 0; e < M * K; ++e) edges[fill[ix[e]]++] = e;
  }

  // Pass 2: x_j's and R_j's gradient from the edges that have j as neighbour (recomputed).
#pragma omp parallel num_threads(nt)
  {
    ArapEdgeBuffers b(T);
    std::vector<double> acc_x(3 * T), acc_r(9 * T);
#pragma omp for schedule(static)
    for (int64_t j = 0; j < M; ++j) {
      std::fill(acc_x.begin(), acc_x.end(), 0.0);
      std::fill(acc_r.begin(), acc_r.end(), 0.0);
      bool any = false;
      for (int64_t n = start[j]; n < start[j + 1]; ++n) {
        const int64_t e = edges[n];
        const double we = wt[e];
        if (we == 0.0) continue;
        any = true;
        edge_coordinates(in, e / K, j, b);
        edge_grad_c(in, b, we, g_coord, g_length);
        for (int64_t t = 0; t < T; ++t) {
          const float* r = in.R + (j * T + t) * 9;
          const double* g = &b.gc[3 * t];
          const double* d = &b.d[3 * t];
          for (int a = 0; a < 3; ++a) {
            acc_x[3 * t + a] -= double(r[3 * a]) * g[0] + double(r[3 * a + 1]) * g[1] + double(r[3 * a + 2]) * g[2];
            for (int q = 0; q < 3; ++q) acc_r[9 * t + 3 * a + q] += d[a] * g[q];  // d c_q / d R_aq = d_a
          }
        }
      }
      if (!any) continue;
      for (int64_t t = 0; t < T; ++t) {
        for (int a = 0; a < 3; ++a) gp[(j * T + t) * 3 + a] += float(acc_x[3 * t + a]);
        for (int q = 0; q < 9; ++q) gr[(j * T + t) * 9 + q] = float(acc_r[9 * t + q]);
      }
    }
  }
  return {g_pos, g_R};
}

// Joins the rasterizer's op namespace (the build's name; see the end of rasterize_cpu.cpp for the macro level).
#define WORLDTREE_LIBRARY_FRAGMENT(ns, m) TORCH_LIBRARY_FRAGMENT(ns, m)
WORLDTREE_LIBRARY_FRAGMENT(TORCH_EXTENSION_NAME, m) {
  m.def("arap_forward", &arap_forward);    // ARAP terms of scaffold trajectories (CPU)
  m.def("arap_backward", &arap_backward);  // their gradients with respect to positions and rotation matrices
}
