// Dual-quaternion-blend (DQB) skinning of Gaussians on the CPU, forward and hand-written backward.
//
// The formula is worldtree.motion.skinning._deform_dual_planes_tensor (docs/motion.md), guards included: for
// Gaussian n (mean p, rotation q) and its K neighbours k (position P_k, radius s_k, dual quaternion (R_k, D_k)):
//   w_k   = exp(-|p - P_k|^2 / (2 max(s_k, 1e-8)^2)) + 1e-6, then max(w_k + c_k, 0), 0 where not valid
//   pivot = first argmax_k w_k (a NaN counts as the maximum, as torch.argmax); (pr, pd) its (R, D) with pr_w >= 0
//   b     = sum_k sign(R_k . pr) w_k / max(W, eps) (R_k, D_k),  W = sum_k w_k
//   mixed with the identity by alpha = clamp(W, 0, 1); the pivot's (pr, pd) instead when |b_real| < tol
//   (r, d) = normalised b (identity where |b_real| <= eps), t = 2 vec(d conj(r))
//   p_t = rotate(r, p) + t (rotate normalises r once more, as quaternion.rotate),  q_t = r q
// The gradients of clamp and where are torch's: a clamp passes the gradient where its input lies inside the
// bounds, bounds included (not for a NaN); a where passes it to the selected branch only.
//
// Why a kernel: written with tensors the blend is some fifty passes over [N, K] planes, forward and backward, and
// was the largest cost of a photometric step on a CPU; here each Gaussian's neighbours are read once. The
// backward recomputes the forward from the inputs (nothing but the inputs is saved).
//
// Layout of the work: Gaussians in blocks of kLanes. Per Gaussian, the neighbour loops (weights, pivot, blend sums;
// in the backward the per-neighbour gradients) run over k. The per-Gaussian tail (normalisation, transform and
// their gradients) is one long chain of dependent operations (two square roots, divisions), latency-bound when
// run one Gaussian at a time; it runs as one SIMD loop over the block's Gaussians instead (`omp simd`, every
// branch a select), several Gaussians per instruction.
//
// Precision: the weights (and the alignment signs) are computed in float32 with the tensor version's operations
// in its order, so that the discrete choices (pivot, ties among weights, clamps, signs) are the float32 tensor
// version's; the blend, the normalisation and all gradients are computed in double and rounded once.
//
// NaN: the normalisation guard (|b_real|^2 > eps^2 in dualquat.normalize) is false for a NaN, which would replace a
// NaN blend by the identity and hide it; here it is written !(|b_real|^2 <= eps^2), and the tensor version adds
// 0 * |b_real|^2 for the same purpose, so a NaN that reaches the blend shows in the outputs.
//
// Same results for any thread count: every Gaussian is computed by one thread, each sum in a fixed order (the
// lanes of the SIMD tail are independent and round like scalar code: no fused multiply-adds, no reassociation),
// and all gradients are per Gaussian or per (Gaussian, neighbour) entry (the sums over Gaussians sharing a node are
// the index_select backward in torch), so no two threads write one value.

#include <ATen/core/Tensor.h>
#include <ATen/ops/empty.h>
#include <c10/util/Exception.h>
#include <torch/library.h>

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <vector>

#include <omp.h>

// Inlined into the SIMD loops (a call would stop their vectorisation).
#define DQB_INLINE inline __attribute__((always_inline))

namespace {

constexpr int kLanes = 16;  // Gaussians per block (SIMD lanes of the tail)

struct DqbInputs {
  const float* pts;    // [N, 3]
  const float* quats;  // [N, 4]
  const float* pos;    // [3, N, K]
  const float* sigma;  // [N, K]
  const float* real;   // [4, N, K]
  const float* dual;   // [4, N, K]
  const bool* valid;   // [N, K], null when every neighbour is valid
  const float* corr;   // [N, K], null without a correction
  int64_t N, K;
  bool mix;
  double eps, tol;
};

// Per-neighbour float32 values of a block's Gaussians (per-thread), lane l's K neighbours from l * K.
struct NbBuffers {
  std::vector<float> d2, var2, e, pre, w, gate, sg;
  std::vector<double> f, t, g, gx, gy, gz;  // one Gaussian's scratch (the blend's terms, the backward's)
  explicit NbBuffers(int64_t K)
      : d2(kLanes * K), var2(kLanes * K), e(kLanes * K), pre(kLanes * K), w(kLanes * K), gate(kLanes * K),
        sg(kLanes * K), f(K), t(K), g(K), gx(K), gy(K), gz(K) {}
};

// Per-Gaussian values of a block (per-thread), structure of arrays [component][lane] for the SIMD tail.
struct Lanes {
  double p[3][kLanes], q[4][kLanes];   // the Gaussian
  double W[kLanes], inv_Wc[kLanes];    // sum of weights, 1 / max(W, eps)
  double b[4][kLanes], bd[4][kLanes];  // normalised blend, before the identity mix
  double pr[4][kLanes], pd[4][kLanes]; // the pivot's (R, D) times ps
  double ps[kLanes];                   // sign that puts the pivot in w >= 0
  int64_t piv[kLanes];                 // pivot neighbour
  double op[3][kLanes], oq[4][kLanes]; // forward: p_t, q_t
  // Backward: upstream gradients in; out the gradients of the normalised blend (after the mix: gb, gbd), of W
  // through alpha (gW), of the pivot's (R, D) through the fallback (gpr, gpd), of p through the rotation (gp) and
  // of q (gq).
  double gP[3][kLanes], gQ[4][kLanes];
  double gb[4][kLanes], gbd[4][kLanes], gW[kLanes], gpr[4][kLanes], gpd[4][kLanes], gp[3][kLanes], gq[4][kLanes];
  // The tail's values (see tail_forward), kept between the forward and the backward of a block.
  double alpha[kLanes];
  // Pivot fallback taken, normalisation guard passed, rotate's guard passed: 1 or 0 (doubles, like every other
  // lane value, so that the SIMD loop has a single element width).
  double degenerate[kLanes], ok[kLanes], ok_rot[kLanes];
  double inv_nrm[kLanes];  // 1 / |br|
  // r = br / |br|, d0 = bd / |br|, s = r . d0, d = d0 - s r
  double r[4][kLanes], d0[4][kLanes], d[4][kLanes], s[kLanes];
  double inv_un[kLanes], u[4][kLanes];  // rotate's renormalisation of r (|r| = 1 up to rounding)
  double tt[3][kLanes], t[3][kLanes];   // 2 vec(u) x p; translation 2 vec(d conj(r))
};

// Four doubles as one value (GCC and Clang vector extension; a target without 256-bit vectors splits it).
typedef double v4d __attribute__((vector_size(32)));

// v[j] += v[j + H] for j < H, then the next level: the vector levels of sum_k.
template <int H>
DQB_INLINE void fold_vectors(v4d* v) {
  for (int j = 0; j < H; ++j) v[j] += v[j + H];
  if constexpr (H > 1) fold_vectors<H / 2>(v);
}

// Sum of x[0..K). For a K known at compile time (a multiple of 4 and a power of two) pairwise,
// t[k] += t[k + h] for h = K/2, ..., 1: the levels down to h = 4 are vector additions of four doubles, the last two
// scalar (a loop over the levels kept the terms in memory, each level waiting for the last one's stores). Else in
// k order. Either way a fixed order, so the same result for any thread count.
template <int KT>
DQB_INLINE double sum_k(const double* __restrict x, int64_t K) {
  if constexpr (KT > 0) {
    static_assert(KT >= 8 && (KT & (KT - 1)) == 0, "sum_k: KT must be a power of two, at least 8");
    v4d v[KT / 4];
    std::memcpy(v, x, sizeof(v));
    fold_vectors<KT / 8>(v);
    return (v[0][0] + v[0][2]) + (v[0][1] + v[0][3]);
  } else {
    double s = 0.0;
    for (int64_t k = 0; k < K; ++k) s += x[k];
    return s;
  }
}

// exp(x) in float32 for x <= 0 (a weight's exponent) or NaN, without a call or a branch so that the weights'
// loop vectorises (the C library's expf, one call per neighbour, took about a fifth of the kernel). Cody-Waite
// reduction by ln 2 and Cephes' degree-5 polynomial: at most 0.98 ulp from exp on every float in [-87.34, 0]
// (checked exhaustively; torch's float32 exp, Sleef's, is a 1-ulp one too). Below -87.34 exp(x) is under FLT_MIN
// and 0 is returned (a weight adds 1e-6 to it, which absorbs any subnormal); -inf gives 0, NaN gives NaN.
DQB_INLINE float exp_nonpos(float x) {
  const float lo = -87.33654f;
  const bool nan = !(x == x);
  float xc = x < lo ? lo : x;
  xc = nan ? 0.0f : xc;  // a NaN must not reach the conversion to int
  const float n = (xc * 1.44269504088896341f + 12582912.0f) - 12582912.0f;  // round to nearest (1.5 * 2^23)
  const float r = (xc - n * 0.693359375f) - n * -2.12194440e-4f;         // x - n ln 2, ln 2 in two parts
  float y = 1.9875691500e-4f;
  y = y * r + 1.3981999507e-3f;
  y = y * r + 8.3334519073e-3f;
  y = y * r + 4.1665795894e-2f;
  y = y * r + 1.6666665459e-1f;
  y = y * r + 5.0000001201e-1f;
  y = y * (r * r) + r + 1.0f;
  const int32_t bits = (int32_t(n) + 127) << 23;  // 2^n, n in [-126, 0]
  float scale;
  std::memcpy(&scale, &bits, sizeof(scale));
  const float e = y * scale;
  return nan ? x : (x < lo ? 0.0f : e);
}

// Skinning weights of one Gaussian in float32, the tensor version's operations in its order: d2, var2, the exp,
// pre = w + c (w without a correction), the masked weight w and gate (1 where a gradient reaches w + c: valid and,
// with a correction, pre >= 0). C and V may be null. The loops vectorise (restrict parameters: GCC ignores
// restrict on local pointers).
template <int KT>
DQB_INLINE void weights(int64_t K, float px, float py, float pz, const float* __restrict P0,
                        const float* __restrict P1, const float* __restrict P2, const float* __restrict S,
                        const float* __restrict C, const bool* __restrict V, float* __restrict d2a,
                        float* __restrict var2a, float* __restrict ea, float* __restrict prea, float* __restrict wa,
                        float* __restrict gate) {
  if constexpr (KT > 0) K = KT;
  for (int64_t k = 0; k < K; ++k) {
    const float dx = px - P0[k], dy = py - P1[k], dz = pz - P2[k];
    const float d2 = dx * dx + dy * dy + dz * dz;
    float sc = S[k];
    sc = sc < 1e-8f ? 1e-8f : sc;  // clamp(min): a NaN stays NaN
    const float var2 = 2.0f * (sc * sc);
    d2a[k] = d2;
    var2a[k] = var2;
    ea[k] = exp_nonpos(-d2 / var2);  // exponent <= 0: underflows to 0, never overflows
  }
  if (C) {
    for (int64_t k = 0; k < K; ++k) {
      const float pre = (ea[k] + 1e-6f) + C[k];
      prea[k] = pre;
      wa[k] = pre < 0.0f ? 0.0f : pre;  // clamp(min): a NaN stays NaN
      gate[k] = pre >= 0.0f ? 1.0f : 0.0f;  // clamp's gradient: inside the bound, the bound included; not a NaN
    }
  } else {
    for (int64_t k = 0; k < K; ++k) {
      wa[k] = prea[k] = ea[k] + 1e-6f;
      gate[k] = 1.0f;
    }
  }
  if (V) {
    for (int64_t k = 0; k < K; ++k) {
      wa[k] = V[k] ? wa[k] : 0.0f;
      gate[k] = V[k] ? gate[k] : 0.0f;
    }
  }
}

// Alignment signs (from the float32 dot product with the pivot, the tensor version's, so its sign choices) and
// the normalised blend b = sum_k sg_k w_k / Wc (R_k, D_k) in double, into bsum[8] = (b_real, b_dual). Every
// neighbour enters, weight 0 included (a NaN in a masked neighbour's transform shows, as in the tensor version).
template <int KT>
DQB_INLINE void blend(int64_t K, const float* __restrict wa, const float* __restrict R0, const float* __restrict R1,
                      const float* __restrict R2, const float* __restrict R3, const float* __restrict D0,
                      const float* __restrict D1, const float* __restrict D2, const float* __restrict D3,
                      const float* prf, double inv_Wc, float* __restrict sga, double* __restrict f,
                      double* __restrict t, double* bsum) {
  if constexpr (KT > 0) K = KT;
  const float p0 = prf[0], p1 = prf[1], p2 = prf[2], p3 = prf[3];
  for (int64_t k = 0; k < K; ++k) {
    const float dt = R0[k] * p0 + R1[k] * p1 + R2[k] * p2 + R3[k] * p3;
    const float sg = dt < 0.0f ? -1.0f : 1.0f;  // a select, not a branch: the signs may be anything
    sga[k] = sg;
    f[k] = double(sg) * (double(wa[k]) * inv_Wc);
  }
  const float* planes[8] = {R0, R1, R2, R3, D0, D1, D2, D3};
  for (int c = 0; c < 8; ++c) {
    const float* __restrict X = planes[c];
    for (int64_t k = 0; k < K; ++k) t[k] = double(X[k]) * f[k];
    bsum[c] = sum_k<KT>(t, K);
  }
}

// One Gaussian's per-neighbour forward (weights, pivot, blend sums) into lane l of the block. KT: K known at
// compile time (loops without remainders, pairwise sums), 0 for any K.
template <int KT>
void neighbours_forward(const DqbInputs& in, int64_t n, int l, NbBuffers& nb, Lanes& L) {
  const int64_t K = KT > 0 ? KT : in.K, NK = in.N * K, base = n * K;
  const float px = in.pts[3 * n], py = in.pts[3 * n + 1], pz = in.pts[3 * n + 2];
  L.p[0][l] = px;
  L.p[1][l] = py;
  L.p[2][l] = pz;
  for (int c = 0; c < 4; ++c) L.q[c][l] = in.quats[4 * n + c];
  float* wa = nb.w.data() + l * K;
  weights<KT>(K, px, py, pz, in.pos + base, in.pos + NK + base, in.pos + 2 * NK + base, in.sigma + base,
              in.corr ? in.corr + base : nullptr, in.valid ? in.valid + base : nullptr, nb.d2.data() + l * K,
              nb.var2.data() + l * K, nb.e.data() + l * K, nb.pre.data() + l * K, wa, nb.gate.data() + l * K);

  // Pivot: the first largest weight, a NaN winning (torch.argmax). Conditional moves rather than branches: where
  // the largest weight sits is random.
  int64_t piv = 0;
  float best = wa[0];
  float total = wa[0];  // NaN iff some weight is (they are >= 0: infinities do not cancel)
  for (int64_t k = 1; k < K; ++k) {
    const bool gt = wa[k] > best;  // false for a NaN: handled below
    best = gt ? wa[k] : best;
    piv = gt ? k : piv;
    total += wa[k];
  }
  if (std::isnan(total))
    for (int64_t k = K - 1; k >= 0; --k) piv = std::isnan(wa[k]) ? k : piv;
  L.piv[l] = piv;
  const float psf = in.real[base + piv] < 0.0f ? -1.0f : 1.0f;
  L.ps[l] = psf;
  float prf[4];
  for (int c = 0; c < 4; ++c) {
    prf[c] = in.real[c * NK + base + piv] * psf;  // exact
    L.pr[c][l] = prf[c];
    L.pd[c][l] = double(in.dual[c * NK + base + piv]) * double(psf);
  }

  double* t = nb.t.data();
  for (int64_t k = 0; k < K; ++k) t[k] = double(wa[k]);
  const double W = sum_k<KT>(t, K);
  const double Wc = W < in.eps ? in.eps : W;  // clamp(min): a NaN stays NaN
  const double inv_Wc = 1.0 / Wc;
  double bsum[8];
  blend<KT>(K, wa, in.real + base, in.real + NK + base, in.real + 2 * NK + base, in.real + 3 * NK + base,
            in.dual + base, in.dual + NK + base, in.dual + 2 * NK + base, in.dual + 3 * NK + base, prf, inv_Wc,
            nb.sg.data() + l * K, nb.f.data(), t, bsum);
  L.W[l] = W;
  L.inv_Wc[l] = inv_Wc;
  for (int c = 0; c < 4; ++c) {
    L.b[c][l] = bsum[c];
    L.bd[c][l] = bsum[4 + c];
  }
}

DQB_INLINE double dot4(const double* a, const double* b) {
  return a[0] * b[0] + a[1] * b[1] + a[2] * b[2] + a[3] * b[3];
}

// Hamilton product a b.
DQB_INLINE void qmul(const double* a, const double* b, double* c) {
  c[0] = a[0] * b[0] - a[1] * b[1] - a[2] * b[2] - a[3] * b[3];
  c[1] = a[0] * b[1] + a[1] * b[0] + a[2] * b[3] - a[3] * b[2];
  c[2] = a[0] * b[2] - a[1] * b[3] + a[2] * b[0] + a[3] * b[1];
  c[3] = a[0] * b[3] + a[1] * b[2] - a[2] * b[1] + a[3] * b[0];
}

DQB_INLINE void cross(const double* a, const double* b, double* c) {
  c[0] = a[1] * b[2] - a[2] * b[1];
  c[1] = a[2] * b[0] - a[0] * b[2];
  c[2] = a[0] * b[1] - a[1] * b[0];
}

// Lane l's tail: the blend mixed, guarded and normalised, and the transform it gives (into L.alpha ... L.t).
template <bool mix>
DQB_INLINE void tail_forward(Lanes& L, int l, double eps2, double tol2) {
  const double W = L.W[l];
  const double alpha = mix ? (W < 0.0 ? 0.0 : (W > 1.0 ? 1.0 : W)) : 1.0;  // clamp: a NaN stays NaN
  L.alpha[l] = alpha;
  double br[4], bd[4];
  for (int c = 0; c < 4; ++c) {
    br[c] = mix ? alpha * L.b[c][l] + (1.0 - alpha) * (c == 0 ? 1.0 : 0.0) : L.b[c][l];
    bd[c] = mix ? alpha * L.bd[c][l] : L.bd[c][l];
  }
  const bool degenerate = dot4(br, br) < tol2;
  L.degenerate[l] = degenerate ? 1.0 : 0.0;
  for (int c = 0; c < 4; ++c) {
    br[c] = degenerate ? L.pr[c][l] : br[c];
    bd[c] = degenerate ? L.pd[c][l] : bd[c];
  }
  // dualquat.normalize; its guard keeps a NaN (see the top).
  const bool ok = !(dot4(br, br) <= eps2);
  L.ok[l] = ok ? 1.0 : 0.0;
  for (int c = 0; c < 4; ++c) {
    br[c] = ok ? br[c] : (c == 0 ? 1.0 : 0.0);
    bd[c] = ok ? bd[c] : 0.0;
  }
  const double inv_nrm = 1.0 / std::sqrt(dot4(br, br));
  L.inv_nrm[l] = inv_nrm;
  double r[4], d0[4], d[4];
  for (int c = 0; c < 4; ++c) {
    r[c] = br[c] * inv_nrm;
    d0[c] = bd[c] * inv_nrm;
  }
  const double s = dot4(r, d0);
  for (int c = 0; c < 4; ++c) d[c] = d0[c] - s * r[c];
  const double rc[4] = {r[0], -r[1], -r[2], -r[3]};
  double m[4];
  qmul(d, rc, m);
  // quaternion.rotate's safe_unit (the same guard, NaN kept).
  const double un2 = dot4(r, r);
  const bool ok_rot = !(un2 <= eps2);
  const double inv_un = ok_rot ? 1.0 / std::sqrt(un2) : 1.0;
  double u[4];
  for (int c = 0; c < 4; ++c) u[c] = ok_rot ? r[c] * inv_un : (c == 0 ? 1.0 : 0.0);
  const double p[3] = {L.p[0][l], L.p[1][l], L.p[2][l]};
  double tt[3];
  cross(u + 1, p, tt);
  for (int c = 0; c < 3; ++c) tt[c] *= 2.0;
  L.s[l] = s;
  L.ok_rot[l] = ok_rot ? 1.0 : 0.0;
  L.inv_un[l] = inv_un;
  for (int c = 0; c < 4; ++c) {
    L.r[c][l] = r[c];
    L.d0[c][l] = d0[c];
    L.d[c][l] = d[c];
    L.u[c][l] = u[c];
  }
  for (int c = 0; c < 3; ++c) {
    L.tt[c][l] = tt[c];
    L.t[c][l] = 2.0 * m[c + 1];
  }
}

// The outputs of lane l: p_t = p + u_w tt + u_v x tt + t, q_t = r q.
DQB_INLINE void tail_outputs(Lanes& L, int l) {
  const double u[4] = {L.u[0][l], L.u[1][l], L.u[2][l], L.u[3][l]};
  const double tt[3] = {L.tt[0][l], L.tt[1][l], L.tt[2][l]};
  double c2[3];
  cross(u + 1, tt, c2);
  for (int c = 0; c < 3; ++c) L.op[c][l] = L.p[c][l] + u[0] * tt[c] + c2[c] + L.t[c][l];
  const double r[4] = {L.r[0][l], L.r[1][l], L.r[2][l], L.r[3][l]};
  const double q[4] = {L.q[0][l], L.q[1][l], L.q[2][l], L.q[3][l]};
  double qt[4];
  qmul(r, q, qt);
  for (int c = 0; c < 4; ++c) L.oq[c][l] = qt[c];
}

// The tail's backward for lane l, from L.gP / L.gQ to L.gb, gbd, gW, gpr, gpd, gp, gq.
template <bool mix>
DQB_INLINE void tail_backward(Lanes& L, int l) {
  const double gP[3] = {L.gP[0][l], L.gP[1][l], L.gP[2][l]};
  const double gQ[4] = {L.gQ[0][l], L.gQ[1][l], L.gQ[2][l], L.gQ[3][l]};
  const double p[3] = {L.p[0][l], L.p[1][l], L.p[2][l]};
  const double r[4] = {L.r[0][l], L.r[1][l], L.r[2][l], L.r[3][l]};
  const double u[4] = {L.u[0][l], L.u[1][l], L.u[2][l], L.u[3][l]};
  const double tt[3] = {L.tt[0][l], L.tt[1][l], L.tt[2][l]};
  // q_t = r q: g_r = g conj(q), g_q = conj(r) g.
  const double qc[4] = {L.q[0][l], -L.q[1][l], -L.q[2][l], -L.q[3][l]};
  const double rc[4] = {r[0], -r[1], -r[2], -r[3]};
  double g_r[4], gq[4];
  qmul(gQ, qc, g_r);
  qmul(rc, gQ, gq);
  for (int c = 0; c < 4; ++c) L.gq[c][l] = gq[c];
  // p_t = p + u_w tt + u_v x tt + t, tt = 2 u_v x p.
  double g_u[4], g_tt[3], c3[3];
  g_u[0] = gP[0] * tt[0] + gP[1] * tt[1] + gP[2] * tt[2];
  cross(gP, u + 1, c3);
  for (int c = 0; c < 3; ++c) g_tt[c] = u[0] * gP[c] + c3[c];
  cross(tt, gP, g_u + 1);
  cross(p, g_tt, c3);
  for (int c = 0; c < 3; ++c) g_u[c + 1] += 2.0 * c3[c];
  cross(g_tt, u + 1, c3);
  for (int c = 0; c < 3; ++c) L.gp[c][l] = gP[c] + 2.0 * c3[c];
  const double ug = dot4(u, g_u);  // u = r / |r|
  const bool ok_rot = L.ok_rot[l] != 0.0;
  const double inv_un = L.inv_un[l];
  for (int c = 0; c < 4; ++c) g_r[c] += ok_rot ? (g_u[c] - u[c] * ug) * inv_un : 0.0;
  // t = 2 vec(d conj(r)): with gm = (0, 2 g_t), g_d = gm r and g_conj(r) = conj(d) gm.
  const double gm[4] = {0.0, 2.0 * gP[0], 2.0 * gP[1], 2.0 * gP[2]};
  const double dc[4] = {L.d[0][l], -L.d[1][l], -L.d[2][l], -L.d[3][l]};
  double g_d[4], gcr[4];
  qmul(gm, r, g_d);
  qmul(dc, gm, gcr);
  g_r[0] += gcr[0];
  for (int c = 1; c < 4; ++c) g_r[c] -= gcr[c];
  // d = d0 - (r . d0) r
  const double d0[4] = {L.d0[0][l], L.d0[1][l], L.d0[2][l], L.d0[3][l]};
  const double s = L.s[l];
  const double rgd = dot4(r, g_d);
  double g_d0[4];
  for (int c = 0; c < 4; ++c) {
    g_d0[c] = g_d[c] - r[c] * rgd;
    g_r[c] -= s * g_d[c] + d0[c] * rgd;
  }
  // r = br / |br|, d0 = bd / |br|; nothing reaches the blend through the identity of the guard.
  const bool ok = L.ok[l] != 0.0;
  const double inv_nrm = L.inv_nrm[l];
  const double a = dot4(g_r, r) + dot4(g_d0, d0);
  double g_br[4], g_bd[4];
  for (int c = 0; c < 4; ++c) {
    g_br[c] = ok ? (g_r[c] - r[c] * a) * inv_nrm : 0.0;
    g_bd[c] = ok ? g_d0[c] * inv_nrm : 0.0;
  }
  // The pivot's fallback takes the gradient where it was used, the blend elsewhere.
  const bool degenerate = L.degenerate[l] != 0.0;
  const double ps = L.ps[l];
  for (int c = 0; c < 4; ++c) {
    L.gpr[c][l] = degenerate ? ps * g_br[c] : 0.0;
    L.gpd[c][l] = degenerate ? ps * g_bd[c] : 0.0;
    g_br[c] = degenerate ? 0.0 : g_br[c];
    g_bd[c] = degenerate ? 0.0 : g_bd[c];
  }
  // The identity mix: b_real = alpha b + (1 - alpha) (1, 0, 0, 0), b_dual = alpha bd.
  const double W = L.W[l];
  double g_alpha = g_br[0] * (L.b[0][l] - 1.0);
  for (int c = 1; c < 4; ++c) g_alpha += g_br[c] * L.b[c][l];
  for (int c = 0; c < 4; ++c) g_alpha += g_bd[c] * L.bd[c][l];
  L.gW[l] = mix && (W >= 0.0) & (W <= 1.0) ? g_alpha : 0.0;  // clamp(W, 0, 1)
  const double alpha = L.alpha[l];  // 1 without the mix
  for (int c = 0; c < 4; ++c) {
    L.gb[c][l] = alpha * g_br[c];
    L.gbd[c][l] = alpha * g_bd[c];
  }
}

// The tails of a block's nl Gaussians, forward (outputs in L.op, L.oq) and forward and backward: SIMD loops over
// the lanes. `mix` is a template argument: a select on a run-time scalar does not vectorise.
template <bool mix>
void tails_forward(Lanes& L, int nl, double eps2, double tol2) {
#pragma omp simd
  for (int l = 0; l < nl; ++l) {
    tail_forward<mix>(L, l, eps2, tol2);
    tail_outputs(L, l);
  }
}

template <bool mix>
void tails_backward(Lanes& L, int nl, double eps2, double tol2) {
#pragma omp simd
  for (int l = 0; l < nl; ++l) {
    tail_forward<mix>(L, l, eps2, tol2);
    tail_backward<mix>(L, l);
  }
}

// Where the gradients go (null: not wanted). A per-thread sink of 8 K floats takes the unwanted ones, so that the
// neighbour loops write without conditions (each output of a loop to its own part: the pointers are restrict).
struct GradOut {
  float *x, *q, *pos, *sig, *re, *du, *co;
};

// The blend's backward for one Gaussian: the transforms' gradients f_k (gb, gbd) (f_k = sg_k w_k / Wc), and the
// gradient of w_k through its coefficient, gw_k = g_coef_k / Wc, and through Wc, -term_k = -g_coef_k w_k / Wc^2.
template <int KT>
DQB_INLINE void blend_backward(int64_t K, const float* __restrict wa, const float* __restrict sga,
                               const float* __restrict R0, const float* __restrict R1, const float* __restrict R2,
                               const float* __restrict R3, const float* __restrict D0, const float* __restrict D1,
                               const float* __restrict D2, const float* __restrict D3, double inv_Wc, const double* gb,
                               const double* gd, float* __restrict GR0, float* __restrict GR1, float* __restrict GR2,
                               float* __restrict GR3, float* __restrict GD0, float* __restrict GD1,
                               float* __restrict GD2, float* __restrict GD3, double* __restrict gw,
                               double* __restrict term) {
  if constexpr (KT > 0) K = KT;
  const double gb0 = gb[0], gb1 = gb[1], gb2 = gb[2], gb3 = gb[3];
  const double gd0 = gd[0], gd1 = gd[1], gd2 = gd[2], gd3 = gd[3];
  for (int64_t k = 0; k < K; ++k) {
    const double coef = double(wa[k]) * inv_Wc, sg = double(sga[k]), f = sg * coef;
    GR0[k] = float(f * gb0);
    GR1[k] = float(f * gb1);
    GR2[k] = float(f * gb2);
    GR3[k] = float(f * gb3);
    GD0[k] = float(f * gd0);
    GD1[k] = float(f * gd1);
    GD2[k] = float(f * gd2);
    GD3[k] = float(f * gd3);
    const double g_coef =
        sg * ((double(R0[k]) * gb0 + double(R1[k]) * gb1 + double(R2[k]) * gb2 + double(R3[k]) * gb3) +
              (double(D0[k]) * gd0 + double(D1[k]) * gd1 + double(D2[k]) * gd2 + double(D3[k]) * gd3));
    gw[k] = g_coef * inv_Wc;
    term[k] = g_coef * (coef * inv_Wc);
  }
}

// The weights' backward for one Gaussian, from d loss / d w_k = gw_k + g_W: the correction's gradient (GC), sigma's
// (GS), the neighbours' positions' (GP*) and the point's terms (gx, gy, gz; summed by the caller).
template <int KT>
DQB_INLINE void weights_backward(int64_t K, const double* __restrict gw, double g_W, const float* __restrict gate,
                                 const float* __restrict d2a, const float* __restrict var2a,
                                 const float* __restrict ea, const float* __restrict S, const float* __restrict P0,
                                 const float* __restrict P1, const float* __restrict P2, double px, double py,
                                 double pz, float* __restrict GC, float* __restrict GS, float* __restrict GP0,
                                 float* __restrict GP1, float* __restrict GP2, double* __restrict gx,
                                 double* __restrict gy, double* __restrict gz) {
  if constexpr (KT > 0) K = KT;
  for (int64_t k = 0; k < K; ++k) {
    // Both sides of every select computed (no conditional loads): the loop then vectorises.
    const double g_in = gw[k] + g_W;
    const double g = gate[k] != 0.0f ? g_in : 0.0;  // the mask's and the clamp's gradients
    GC[k] = float(g);
    const double inv_var2 = 1.0 / double(var2a[k]);
    const double g_a = g * double(ea[k]);  // a = -d2 / var2
    const double g_d2 = -g_a * inv_var2;
    const double dx = 2.0 * (px - double(P0[k])) * g_d2;
    const double dy = 2.0 * (py - double(P1[k])) * g_d2;
    const double dz = 2.0 * (pz - double(P2[k])) * g_d2;
    gx[k] = dx;
    gy[k] = dy;
    gz[k] = dz;
    GP0[k] = float(-dx);
    GP1[k] = float(-dy);
    GP2[k] = float(-dz);
    // In double d2 / var2^2 stays finite (d2 <= FLT_MAX, var2 >= 2e-16), so g_a = 0 gives 0, not 0 * inf.
    const double g_var2 = g_a * ((double(d2a[k]) * inv_var2) * inv_var2);
    const float sk = S[k];
    const float g_s = float(g_var2 * 4.0 * double(sk));
    GS[k] = sk >= 1e-8f ? g_s : 0.0f;  // clamp(sigma, min=1e-8)
  }
}

// Lane l's per-neighbour backward: writes the gradients of Gaussian n's (Gaussian, neighbour) entries, of p and of
// q. KT: K known at compile time, 0 for any K.
template <int KT>
void neighbours_backward(const DqbInputs& in, int64_t n, int l, NbBuffers& nb, const Lanes& L, const GradOut& o,
                         float* sink) {
  const int64_t K = KT > 0 ? KT : in.K, NK = in.N * K, base = n * K;
  auto plane = [&](float* t, int c, int slot) { return t ? t + c * NK + base : sink + slot * K; };
  const float* wa = nb.w.data() + l * K;
  const float* sga = nb.sg.data() + l * K;
  float* gr[4] = {plane(o.re, 0, 0), plane(o.re, 1, 1), plane(o.re, 2, 2), plane(o.re, 3, 3)};
  float* gd[4] = {plane(o.du, 0, 4), plane(o.du, 1, 5), plane(o.du, 2, 6), plane(o.du, 3, 7)};
  const double inv_Wc = L.inv_Wc[l];
  const double gb[4] = {L.gb[0][l], L.gb[1][l], L.gb[2][l], L.gb[3][l]};
  const double gbd[4] = {L.gbd[0][l], L.gbd[1][l], L.gbd[2][l], L.gbd[3][l]};
  double* gw = nb.g.data();
  double* term = nb.t.data();
  blend_backward<KT>(K, wa, sga, in.real + base, in.real + NK + base, in.real + 2 * NK + base,
                     in.real + 3 * NK + base, in.dual + base, in.dual + NK + base, in.dual + 2 * NK + base,
                     in.dual + 3 * NK + base, inv_Wc, gb, gbd, gr[0], gr[1], gr[2], gr[3], gd[0], gd[1], gd[2], gd[3],
                     gw, term);
  if (L.degenerate[l] != 0.0) {  // the pivot's fallback (then gb = gbd = 0)
    const int64_t piv = L.piv[l];
    const double f = double(sga[piv]) * (double(wa[piv]) * inv_Wc);
    for (int c = 0; c < 4; ++c) {
      gr[c][piv] = float(f * gb[c] + L.gpr[c][l]);
      gd[c][piv] = float(f * gbd[c] + L.gpd[c][l]);
    }
  }
  double g_p[3] = {L.gp[0][l], L.gp[1][l], L.gp[2][l]};
  if (o.pos || o.sig || o.co || o.x) {  // the weights' gradient reaches these only
    const double g_Wc = -sum_k<KT>(term, K);  // W = sum_k w_k, through Wc = max(W, eps)
    const double g_W = L.gW[l] + (L.W[l] >= in.eps ? g_Wc : 0.0);
    double *gx = nb.gx.data(), *gy = nb.gy.data(), *gz = nb.gz.data();
    weights_backward<KT>(K, gw, g_W, nb.gate.data() + l * K, nb.d2.data() + l * K, nb.var2.data() + l * K,
                         nb.e.data() + l * K, in.sigma + base, in.pos + base, in.pos + NK + base,
                         in.pos + 2 * NK + base, L.p[0][l], L.p[1][l], L.p[2][l], plane(o.co, 0, 0),
                         plane(o.sig, 0, 1), plane(o.pos, 0, 2), plane(o.pos, 1, 3), plane(o.pos, 2, 4), gx, gy, gz);
    g_p[0] += sum_k<KT>(gx, K);
    g_p[1] += sum_k<KT>(gy, K);
    g_p[2] += sum_k<KT>(gz, K);
  }
  if (o.x)
    for (int c = 0; c < 3; ++c) o.x[3 * n + c] = float(g_p[c]);
  if (o.q)
    for (int c = 0; c < 4; ++c) o.q[4 * n + c] = float(L.gq[c][l]);
}

void check_inputs(const at::Tensor& pts, const at::Tensor& quats, const at::Tensor& pos, const at::Tensor& sigma,
                  const at::Tensor& real, const at::Tensor& dual, const at::Tensor& valid, const at::Tensor& corr,
                  bool has_valid, bool has_corr) {
  auto f32 = [](const at::Tensor& t) {
    return t.scalar_type() == at::kFloat && t.is_contiguous() && t.device().is_cpu();
  };
  TORCH_CHECK(pts.dim() == 2 && pts.size(1) == 3 && f32(pts), "dqb: points must be a contiguous float32 [N, 3] tensor");
  const int64_t N = pts.size(0);
  TORCH_CHECK(sigma.dim() == 2 && sigma.size(0) == N && f32(sigma), "dqb: nb_sigma must be a float32 [N, K] tensor");
  const int64_t K = sigma.size(1);
  TORCH_CHECK(K >= 1, "dqb: needs K >= 1 neighbours");
  TORCH_CHECK(quats.sizes() == at::IntArrayRef({N, 4}) && f32(quats), "dqb: quats must be a float32 [N, 4] tensor");
  TORCH_CHECK(pos.sizes() == at::IntArrayRef({3, N, K}) && f32(pos), "dqb: nb_pos_ref must be a float32 [3, N, K]");
  TORCH_CHECK(real.sizes() == at::IntArrayRef({4, N, K}) && f32(real), "dqb: nb_real must be a float32 [4, N, K]");
  TORCH_CHECK(dual.sizes() == at::IntArrayRef({4, N, K}) && f32(dual), "dqb: nb_dual must be a float32 [4, N, K]");
  if (has_valid)
    TORCH_CHECK(valid.sizes() == sigma.sizes() && valid.scalar_type() == at::kBool && valid.is_contiguous() &&
                    valid.device().is_cpu(),
                "dqb: valid must be a contiguous bool CPU [N, K] tensor");
  if (has_corr) TORCH_CHECK(corr.sizes() == sigma.sizes() && f32(corr), "dqb: correction must be a float32 [N, K]");
}

DqbInputs dqb_inputs(const at::Tensor& pts, const at::Tensor& quats, const at::Tensor& pos, const at::Tensor& sigma,
                     const at::Tensor& real, const at::Tensor& dual, const at::Tensor& valid, const at::Tensor& corr,
                     bool has_valid, bool has_corr, bool mix, double eps, double tol) {
  check_inputs(pts, quats, pos, sigma, real, dual, valid, corr, has_valid, has_corr);
  return DqbInputs{pts.data_ptr<float>(),
                   quats.data_ptr<float>(),
                   pos.data_ptr<float>(),
                   sigma.data_ptr<float>(),
                   real.data_ptr<float>(),
                   dual.data_ptr<float>(),
                   has_valid ? valid.data_ptr<bool>() : nullptr,
                   has_corr ? corr.data_ptr<float>() : nullptr,
                   pts.size(0),
                   sigma.size(1),
                   mix,
                   eps,
                   tol};
}

// The forward over all blocks, threads splitting the blocks.
template <int KT>
void forward_blocks(const DqbInputs& in, float* op, float* oq, int64_t threads) {
  const int64_t N = in.N, blocks = (N + kLanes - 1) / kLanes;
  const double eps2 = in.eps * in.eps, tol2 = in.tol * in.tol;
#pragma omp parallel num_threads(int(std::max<int64_t>(threads, 1)))
  {
    NbBuffers nb(in.K);
    Lanes L;
#pragma omp for schedule(static)
    for (int64_t blk = 0; blk < blocks; ++blk) {
      const int64_t n0 = blk * kLanes;
      const int nl = int(std::min<int64_t>(kLanes, N - n0));
      for (int l = 0; l < nl; ++l) neighbours_forward<KT>(in, n0 + l, l, nb, L);
      if (in.mix)
        tails_forward<true>(L, nl, eps2, tol2);
      else
        tails_forward<false>(L, nl, eps2, tol2);
      for (int l = 0; l < nl; ++l) {
        for (int c = 0; c < 3; ++c) op[3 * (n0 + l) + c] = float(L.op[c][l]);
        for (int c = 0; c < 4; ++c) oq[4 * (n0 + l) + c] = float(L.oq[c][l]);
      }
    }
  }
}

// The backward over all blocks: the forward recomputed, then the tails' backward, then the neighbours'.
template <int KT>
void backward_blocks(const DqbInputs& in, const float* gp_in, const float* gq_in, const GradOut& out,
                     int64_t threads) {
  const int64_t N = in.N, blocks = (N + kLanes - 1) / kLanes;
  const double eps2 = in.eps * in.eps, tol2 = in.tol * in.tol;
#pragma omp parallel num_threads(int(std::max<int64_t>(threads, 1)))
  {
    NbBuffers nb(in.K);
    Lanes L;
    std::vector<float> sink(8 * in.K);
#pragma omp for schedule(static)
    for (int64_t blk = 0; blk < blocks; ++blk) {
      const int64_t n0 = blk * kLanes;
      const int nl = int(std::min<int64_t>(kLanes, N - n0));
      for (int l = 0; l < nl; ++l) {
        neighbours_forward<KT>(in, n0 + l, l, nb, L);
        for (int c = 0; c < 3; ++c) L.gP[c][l] = gp_in[3 * (n0 + l) + c];
        for (int c = 0; c < 4; ++c) L.gQ[c][l] = gq_in[4 * (n0 + l) + c];
      }
      if (in.mix)
        tails_backward<true>(L, nl, eps2, tol2);
      else
        tails_backward<false>(L, nl, eps2, tol2);
      for (int l = 0; l < nl; ++l) neighbours_backward<KT>(in, n0 + l, l, nb, L, out, sink.data());
    }
  }
}

}  // namespace

// (points_t [N, 3], quats_t [N, 4]) float32. valid / correction are ignored (may be empty) unless has_valid /
// has_corr.
std::vector<at::Tensor> dqb_forward(at::Tensor pts, at::Tensor quats, at::Tensor pos, at::Tensor sigma,
                                    at::Tensor real, at::Tensor dual, at::Tensor valid, at::Tensor corr,
                                    bool has_valid, bool has_corr, bool mix_identity, double eps,
                                    double degenerate_tol, int64_t threads) {
  const DqbInputs in = dqb_inputs(pts, quats, pos, sigma, real, dual, valid, corr, has_valid, has_corr, mix_identity,
                                  eps, degenerate_tol);
  auto out_p = at::empty({in.N, 3}, pts.options());
  auto out_q = at::empty({in.N, 4}, pts.options());
  float* op = out_p.data_ptr<float>();
  float* oq = out_q.data_ptr<float>();
  // The usual neighbour counts get loops of a known length (the scaffold's graph rows have 16).
  if (in.K == 8)
    forward_blocks<8>(in, op, oq, threads);
  else if (in.K == 16)
    forward_blocks<16>(in, op, oq, threads);
  else
    forward_blocks<0>(in, op, oq, threads);
  return {out_p, out_q};
}

// Gradients (points [N, 3], quats [N, 4], nb_pos_ref [3, N, K], nb_sigma [N, K], nb_real [4, N, K], nb_dual
// [4, N, K], correction [N, K]) for upstream gradients g_pts [N, 3], g_quats [N, 4]. Bit i of `needs` asks for the
// i-th of them; the others come back empty ([0]), as does the correction's without has_corr.
std::vector<at::Tensor> dqb_backward(at::Tensor pts, at::Tensor quats, at::Tensor pos, at::Tensor sigma,
                                     at::Tensor real, at::Tensor dual, at::Tensor valid, at::Tensor corr,
                                     bool has_valid, bool has_corr, bool mix_identity, double eps,
                                     double degenerate_tol, at::Tensor g_pts, at::Tensor g_quats, int64_t needs,
                                     int64_t threads) {
  const DqbInputs in = dqb_inputs(pts, quats, pos, sigma, real, dual, valid, corr, has_valid, has_corr, mix_identity,
                                  eps, degenerate_tol);
  const int64_t N = in.N, K = in.K;
  TORCH_CHECK(g_pts.sizes() == pts.sizes() && g_pts.scalar_type() == at::kFloat && g_pts.is_contiguous(),
              "dqb_backward: g_pts must be a contiguous float32 [N, 3] tensor");
  TORCH_CHECK(g_quats.sizes() == quats.sizes() && g_quats.scalar_type() == at::kFloat && g_quats.is_contiguous(),
              "dqb_backward: g_quats must be a contiguous float32 [N, 4] tensor");
  if (!has_corr) needs &= ~int64_t(64);
  auto opts = pts.options();
  auto make = [&](int bit, at::IntArrayRef shape) {
    return (needs >> bit) & 1 ? at::empty(shape, opts) : at::empty({0}, opts);
  };
  auto gx = make(0, {N, 3}), gq = make(1, {N, 4}), gpos = make(2, {3, N, K}), gsig = make(3, {N, K}),
       greal = make(4, {4, N, K}), gdual = make(5, {4, N, K}), gcorr = make(6, {N, K});
  auto ptr = [](at::Tensor& t) { return t.numel() ? t.data_ptr<float>() : nullptr; };
  const GradOut out{ptr(gx), ptr(gq), ptr(gpos), ptr(gsig), ptr(greal), ptr(gdual), ptr(gcorr)};
  const float* gp_in = g_pts.data_ptr<float>();
  const float* gq_in = g_quats.data_ptr<float>();
  if (K == 8)
    backward_blocks<8>(in, gp_in, gq_in, out, threads);
  else if (K == 16)
    backward_blocks<16>(in, gp_in, gq_in, out, threads);
  else
    backward_blocks<0>(in, gp_in, gq_in, out, threads);
  return {gx, gq, gpos, gsig, greal, gdual, gcorr};
}

// Joins the rasterizer's op namespace (the build's name; see the end of rasterize_cpu.cpp for the macro level).
#define WORLDTREE_LIBRARY_FRAGMENT(ns, m) TORCH_LIBRARY_FRAGMENT(ns, m)
WORLDTREE_LIBRARY_FRAGMENT(TORCH_EXTENSION_NAME, m) {
  m.def("dqb_forward", &dqb_forward);    // DQB skinning of Gaussians (CPU, float32)
  m.def("dqb_backward", &dqb_backward);  // its gradients
}
