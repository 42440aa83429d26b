// Gaussian rasterizer on the CPU: EWA projection (per Gaussian) and tile compositing (per tile), forward and
// hand-written backward, OpenMP-parallel. The projection follows worldtree/render/projection.py (its oracle).
//
// Same image formation as worldtree/render/reference.py (the oracle): Gaussians binned into 16x16 tiles by
// their bounding square, front to back per tile (ties by index); per pixel alpha = min(0.99, o exp(power)),
// skipped when power > 0 or alpha < 1/255; compositing stops before T would fall below 1e-4. A tile's list
// leaves out the Gaussians whose alpha is below 1/255 on every pixel of the tile (outside their reach box,
// below), which every pixel would skip anyway: the result is the same, the lists are shorter.
// Pixel (i, j) has its centre at (u, v) = (j, i).
//
// Layout: the forward bins once (Bins: per visible Gaussian a 64-byte record in depth order, per (tile,
// Gaussian) pair an 8-byte reference to it and the tile's part of the reach box) and composites tile by tile,
// reading the records through the pairs; the backward reads the same records and pairs (saved by the forward).
//
// Backward: per pixel, walk the composited Gaussians back to front, recovering T before each one by division
// (1 - alpha >= 0.01); d out / d alpha_k = T_k (c_k - B_k) for every channel (r, g, b over the background,
// depth over 0, and the alpha channel as colour 1 over 0), B_k the normalised colour behind it, of which only
// the sum weighted by dL/d(out) is kept (backward_impl). Each (tile, Gaussian) pair owns a gradient slot, so
// tiles run in parallel without atomics, and the slots are summed per Gaussian in tile order: deterministic.

// Light ATen headers instead of <torch/extension.h> (which takes about 20 s of a cold build just to parse); the
// functions are registered as torch custom ops (torch.ops.<TORCH_EXTENSION_NAME>.<name>), not as a pybind11 module.
#define TORCH_ASSERT_ONLY_METHOD_OPERATORS
#include <ATen/Dispatch.h>
#include <ATen/core/Tensor.h>
#include <ATen/ops/empty.h>
#include <ATen/ops/zeros.h>
#include <torch/library.h>

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <limits>
#include <numeric>
#include <type_traits>
#include <vector>

#ifdef _OPENMP
#include <omp.h>
#endif
#if defined(__x86_64__) || defined(__i386__)
#include <immintrin.h>
#endif

namespace {

constexpr int TILE = 16;
constexpr int TILE_PIX = TILE * TILE;
constexpr int NGRAD = 10;  // per-pair gradient slot: mx, my, a, b, c, o, r, g, b, z

template <typename T>
struct Consts {
  static constexpr T alpha_max = T(0.99);
  static constexpr T alpha_min = T(1.0) / T(255.0);
  static constexpr T t_min = T(1e-4);
};

// The pixel box outside which a Gaussian's alpha is certainly < 1/255, [x0, x1) x [y0, y1), computed once per
// Gaussian in double and intersected with the image and the tiles by span_of. Two steps:
// - loose: the bounding box of the ellipse d^T C d <= L, L = 2 ln(255 o) + 1e-3 (a slack on the exponent far
//   above float rounding), widened by one pixel, so the exact per-pixel tests decide every borderline case;
// - tight, inside it: a pixel composites only if alpha = o exp(power) >= 1/255 with power and exp as the kernel
//   computes them in T, so only if that power is at least thr = -ln(255 o) - 1e-3 (the margin is far above the
//   error of the exp and of the rounding of o exp). On the loose box that power is within E = 4 eps (|a| ex^2 +
//   |c| ey^2 + 2 |b| ex ey) of the exact one (eps = T's machine epsilon; a few roundings of terms at most that
//   large), so compositing needs d^T C d <= L + 1e-3 + 2 E: the integer pixels of that ellipse's bounding box
//   (widened by a few rounding units). This leaves out the rows and columns the loose box adds (about a third
//   of them on the benchmark scene) and the tiles met only by those.
// An unusable conic reaches everywhere (-inf, inf); an opacity below 1/255 (or NaN) reaches nowhere.
struct Reach {
  double x0, x1, y0, y1;
};

template <typename T>
inline Reach reach_of(T mx, T my, T a, T b, T c, T o) {
  if (!(o >= Consts<T>::alpha_min)) return {1.0, 0.0, 1.0, 0.0};
  const double inf = std::numeric_limits<double>::infinity();
  const double det = double(a) * double(c) - double(b) * double(b);
  const double L = 2.0 * std::log(255.0 * double(o)) + 1e-3;  // alpha >= 1/255 needs d^T C d <= L
  if (det > 0 && std::isfinite(det) && L >= 0) {
    const double ex = std::sqrt(L * double(c) / det) + 1.0, ey = std::sqrt(L * double(a) / det) + 1.0;
    if (std::isfinite(ex) && std::isfinite(ey)) {
      const double eps = std::numeric_limits<T>::epsilon();
      const double E = 4.0 * eps * (std::abs(double(a)) * ex * ex + std::abs(double(c)) * ey * ey +
                                    2.0 * std::abs(double(b)) * ex * ey);
      const double Lt = (L + 1e-3 + 2.0 * E) * (1.0 + 4.0 * eps) + 1e-9;
      const double hx = std::sqrt(Lt * double(c) / det) * (1.0 + 1e-12) + 1e-9;
      const double hy = std::sqrt(Lt * double(a) / det) * (1.0 + 1e-12) + 1e-9;
      if (hx <= ex && hy <= ey)
        return {std::ceil(double(mx) - hx), std::floor(double(mx) + hx) + 1.0, std::ceil(double(my) - hy),
                std::floor(double(my) + hy) + 1.0};
      return {std::floor(double(mx) - ex), std::ceil(double(mx) + ex) + 1.0, std::floor(double(my) - ey),
              std::ceil(double(my) + ey) + 1.0};
    }
  }
  return {-inf, inf, -inf, inf};
}

// Tiles touched by a Gaussian's bounding square, as in projection.tile_rect (same precision, same formula).
template <typename T>
inline void tile_rect(T u, T v, T r, int tw, int th, int& x0, int& x1, int& y0, int& y1) {
  auto clampi = [](T x, int hi) -> int { return static_cast<int>(std::min<T>(std::max<T>(x, T(0)), T(hi))); };
  const T h = T(0.5), ts = T(TILE);
  x0 = clampi(std::floor((u + h - r) / ts), tw);
  x1 = clampi(std::ceil((u + h + r) / ts), tw);
  y0 = clampi(std::floor((v + h - r) / ts), th);
  y1 = clampi(std::ceil((v + h + r) / ts), th);
}

// A listed Gaussian as the compositing loops read it: everything the forward and the backward need of it in one
// record (one cache line in float), the records in depth order. The loops read them through the tile lists
// instead of gathering from six input arrays (about a cache miss per array and pair), and fetch a couple of
// pairs ahead.
template <typename T>
struct alignas(sizeof(T) == 4 ? 64 : 32) Gauss {
  T mx, my, ca, cb, cc, o, cr, cg, cbl, z;
  int32_t g;       // Gaussian index
  int32_t first;   // its pairs are Bins::gpos[first .. first + npairs), in tile order
  int32_t npairs;
};
static_assert(sizeof(Gauss<float>) == 64 && sizeof(Gauss<double>) == 96, "record layout");

// One (tile, Gaussian) pair of a tile's list: the Gaussian's record (its place in depth order) and the tile's
// pixels inside its reach box, relative to the tile: [x0, x1) x [y0, y1).
struct Ref {
  int32_t k;
  uint8_t x0, x1, y0, y1;
};
static_assert(sizeof(Ref) == 8, "pair layout");

template <typename T>
struct Bins {
  std::vector<int64_t> start;  // [n_tiles]
  std::vector<int64_t> count;  // [n_tiles]
  at::Tensor ids;              // [M] int32 Gaussian index per (tile, Gaussian) pair, front to back within a tile
  at::Tensor refs;             // [M] int64: the pairs (Ref) in the same order
  at::Tensor recs;             // [visible * sizeof(Gauss<T>)] uint8: the records, front to back
  at::Tensor gpos;             // [M] int32: the pairs (their place in the tile lists) grouped by Gaussian
};

// The Gaussians with radius > 0 front to back, ties by index (what a stable sort by depth gives): an LSD radix
// sort (8-bit digits, stable) of the depth's bit pattern mapped to an unsigned integer of the same order (a total
// order, NaN included), the keys taken in index order.
template <typename T>
std::vector<int32_t> depth_order(const T* depths, const int32_t* radii, int64_t n) {
  using U = std::conditional_t<sizeof(T) == 4, uint32_t, uint64_t>;
  constexpr U sign = U(1) << (8 * sizeof(U) - 1);
  std::vector<U> key, key2;
  std::vector<int32_t> idx, idx2;
  key.reserve(n), idx.reserve(n);
  for (int64_t i = 0; i < n; ++i)
    if (radii[i] > 0) {
      const T d = depths[i] + T(0);  // -0 becomes +0, so equal depths stay ties
      U u;
      std::memcpy(&u, &d, sizeof u);
      key.push_back((u & sign) ? U(~u) : U(u | sign));
      idx.push_back(static_cast<int32_t>(i));
    }
  const size_t m = key.size();
  key2.resize(m), idx2.resize(m);
  for (int shift = 0; shift < int(8 * sizeof(U)) && m > 1; shift += 8) {
    size_t pos[256] = {};
    for (size_t k = 0; k < m; ++k) ++pos[(key[k] >> shift) & 255];
    if (pos[(key[0] >> shift) & 255] == m) continue;  // one digit for all: the pass would change nothing
    size_t acc = 0;
    for (int d = 0; d < 256; ++d) {
      const size_t c = pos[d];
      pos[d] = acc;
      acc += c;
    }
    for (size_t k = 0; k < m; ++k) {
      const size_t p = pos[(key[k] >> shift) & 255]++;
      key2[p] = key[k], idx2[p] = idx[k];
    }
    key.swap(key2), idx.swap(idx2);
  }
  return idx;
}

// Per Gaussian, where it is listed: the tiles [tx0, tx1) x [ty0, ty1) that its bounding square touches
// (tile_rect) and its reach box meets, and the reach box's pixels inside the image, [rx0, rx1) x [ry0, ry1).
// The tiles a box meets form a rectangle, so this is the per-tile test max(px0, x0) < min(px1, x1) (rows
// likewise) of the tile's pixels [px0, px1) and the box, done once per Gaussian.
struct Span {
  int32_t tx0, tx1, ty0, ty1, rx0, rx1, ry0, ry1;
};

template <typename T>
Span span_of(const T* means2d, const T* conics, const T* opac, const int32_t* radii, int64_t g, int width,
             int height) {
  Span S{0, 0, 0, 0, 0, 0, 0, 0};
  if (radii[g] <= 0) return S;
  const Reach R = reach_of<T>(means2d[2 * g], means2d[2 * g + 1], conics[3 * g], conics[3 * g + 1],
                              conics[3 * g + 2], opac[g]);
  // Clamped to the image; a NaN bound (a NaN mean) does not limit, as the comparisons above would not.
  auto lower = [](double v, int hi) { return !(v > 0) ? 0 : v < hi ? static_cast<int>(v) : hi; };
  auto upper = [](double v, int hi) { return !(v < hi) ? hi : v > 0 ? static_cast<int>(v) : 0; };
  S.rx0 = lower(R.x0, width), S.rx1 = upper(R.x1, width);
  S.ry0 = lower(R.y0, height), S.ry1 = upper(R.y1, height);
  if (!(S.rx0 < S.rx1 && S.ry0 < S.ry1)) return S;
  const int tw = (width + TILE - 1) / TILE, th = (height + TILE - 1) / TILE;
  int x0, x1, y0, y1;
  tile_rect<T>(means2d[2 * g], means2d[2 * g + 1], static_cast<T>(radii[g]), tw, th, x0, x1, y0, y1);
  S.tx0 = std::max(x0, S.rx0 / TILE), S.tx1 = std::min(x1, (S.rx1 + TILE - 1) / TILE);
  S.ty0 = std::max(y0, S.ry0 / TILE), S.ty1 = std::min(y1, (S.ry1 + TILE - 1) / TILE);
  if (!(S.tx0 < S.tx1 && S.ty0 < S.ty1)) S.tx1 = S.tx0, S.ty1 = S.ty0;
  return S;
}

// Tile lists and pair records: the visible Gaussians sorted front to back; in that order (parallel), each one's
// record and span, reading its inputs once; the depth order cut into one chunk per thread, each chunk's pairs
// counted per tile (parallel); each chunk's first slot in every tile from the counts (a prefix sum over tiles,
// then chunks); each chunk's records written (parallel). Every tile's list comes out front to back whatever the
// number of chunks.
template <typename T>
Bins<T> bin_gaussians(const T* means2d, const T* conics, const T* opac, const T* colors, const T* depths,
                      const int32_t* radii, int64_t n, int width, int height, int threads) {
  const int tw = (width + TILE - 1) / TILE, th = (height + TILE - 1) / TILE;
  const int64_t nt = int64_t(tw) * th;
  const std::vector<int32_t> order = depth_order<T>(depths, radii, n);
  const int64_t nv = static_cast<int64_t>(order.size());
  Bins<T> bins;
  bins.recs = at::empty({nv * int64_t(sizeof(Gauss<T>))}, at::dtype(at::kByte));
  Gauss<T>* rec = reinterpret_cast<Gauss<T>*>(bins.recs.template data_ptr<uint8_t>());
  std::vector<Span> span(nv);
#pragma omp parallel for schedule(static) num_threads(threads)
  for (int64_t k = 0; k < nv; ++k) {
    if (k + 8 < nv) {  // the inputs are read in depth order, i.e. scattered: fetch a few Gaussians ahead
      const int32_t h = order[k + 8];
      __builtin_prefetch(means2d + 2 * h), __builtin_prefetch(conics + 3 * h), __builtin_prefetch(opac + h);
      __builtin_prefetch(colors + 3 * h), __builtin_prefetch(depths + h), __builtin_prefetch(radii + h);
    }
    const int32_t g = order[k];
    span[k] = span_of<T>(means2d, conics, opac, radii, g, width, height);
    Gauss<T>& R = rec[k];
    R.mx = means2d[2 * g], R.my = means2d[2 * g + 1];
    R.ca = conics[3 * g], R.cb = conics[3 * g + 1], R.cc = conics[3 * g + 2];
    R.o = opac[g];
    R.cr = colors[3 * g], R.cg = colors[3 * g + 1], R.cbl = colors[3 * g + 2];
    R.z = depths[g];
    R.g = g;
    R.npairs = (span[k].tx1 - span[k].tx0) * (span[k].ty1 - span[k].ty0);
  }
  {
    int64_t first = 0;
    for (int64_t k = 0; k < nv; ++k) {
      rec[k].first = static_cast<int32_t>(first);
      first += rec[k].npairs;
    }
    TORCH_CHECK(first < (int64_t(1) << 31), "more than 2^31 (tile, Gaussian) pairs; use the reference backend");
  }
  const int nchunk = std::max(1, threads);
  std::vector<int64_t> slot(nchunk * nt, 0);  // [chunk][tile]: pairs, then first slot
#pragma omp parallel for schedule(static, 1) num_threads(threads)
  for (int c = 0; c < nchunk; ++c) {
    int64_t* cnt = slot.data() + c * nt;
    for (int64_t k = nv * c / nchunk; k < nv * (c + 1) / nchunk; ++k) {
      const Span& S = span[k];
      for (int ty = S.ty0; ty < S.ty1; ++ty)
        for (int tx = S.tx0; tx < S.tx1; ++tx) ++cnt[int64_t(ty) * tw + tx];
    }
  }
  bins.count.assign(nt, 0);
  bins.start.assign(nt, 0);
  int64_t total = 0;
  for (int64_t t = 0; t < nt; ++t) {
    bins.start[t] = total;
    for (int c = 0; c < nchunk; ++c) {
      const int64_t k = slot[c * nt + t];
      slot[c * nt + t] = total;
      total += k;
    }
    bins.count[t] = total - bins.start[t];
  }
  bins.ids = at::empty({total}, at::dtype(at::kInt));
  bins.refs = at::empty({total}, at::dtype(at::kLong));
  bins.gpos = at::empty({total}, at::dtype(at::kInt));
  int32_t* ids = bins.ids.template data_ptr<int32_t>();
  int32_t* gpos = bins.gpos.template data_ptr<int32_t>();
  Ref* refs = reinterpret_cast<Ref*>(bins.refs.template data_ptr<int64_t>());
#pragma omp parallel for schedule(static, 1) num_threads(threads)
  for (int c = 0; c < nchunk; ++c) {
    int64_t* fill = slot.data() + c * nt;
    for (int64_t k = nv * c / nchunk; k < nv * (c + 1) / nchunk; ++k) {
      const Span& S = span[k];
      Ref R;
      R.k = static_cast<int32_t>(k);
      int32_t* pos = gpos + rec[k].first;
      for (int ty = S.ty0; ty < S.ty1; ++ty) {
        const int py0 = ty * TILE, py1 = std::min(py0 + TILE, height);
        R.y0 = static_cast<uint8_t>(std::max(py0, S.ry0) - py0);
        R.y1 = static_cast<uint8_t>(std::min(py1, S.ry1) - py0);
        for (int tx = S.tx0; tx < S.tx1; ++tx) {
          const int px0 = tx * TILE, px1 = std::min(px0 + TILE, width);
          R.x0 = static_cast<uint8_t>(std::max(px0, S.rx0) - px0);
          R.x1 = static_cast<uint8_t>(std::min(px1, S.rx1) - px0);
          const int64_t j = fill[int64_t(ty) * tw + tx]++;
          ids[j] = order[k];
          refs[j] = R;
          *pos++ = static_cast<int32_t>(j);
        }
      }
    }
  }
  return bins;
}

// SIMD width: a tile row (16 pixels) is TILE / W vectors of W lanes. A GCC vector wider than the target's
// registers is lowered to slow generic code (a 16-float row vector ran about 15x slower on AVX2 than on
// AVX-512), so the lane count follows the target, except that AVX-512 targets use 256-bit vectors too (with
// AVX-512VL's mask registers): most reach boxes are narrower than a tile, so 8-lane half rows skip the half a
// Gaussian does not reach, and on Zen 4, where a 512-bit operation costs two 256-bit ones, 16-lane rows were
// 6 % (forward) and 15-25 % (backward) slower on the benchmark scene.
#if defined(__AVX__)
constexpr int VBYTES = 32;
#else
constexpr int VBYTES = 16;
#endif

template <typename T>
struct Simd {
  static constexpr int W = std::min<int>(VBYTES / sizeof(T), TILE);  // lanes per vector
  static constexpr int N = TILE / W;                                  // vectors per tile row
  typedef T V __attribute__((vector_size(W * sizeof(T))));
  typedef std::conditional_t<sizeof(T) == 4, int32_t, int64_t> I;
  typedef I M __attribute__((vector_size(W * sizeof(T))));
};

template <typename V, typename S>
inline V splat(S x) {
  V v = {};
  return v + static_cast<decltype(v[0] + 0)>(x);
}

// Sum of the lanes, as a tree: the two halves added, recursively (log2(W) vector additions instead of a chain of
// W - 1 scalar ones, ten of which ended every pair of the backward).
template <typename V>
inline auto hsum(const V& v) {
  using E = std::remove_cv_t<std::remove_reference_t<decltype(v[0])>>;
  constexpr int n = int(sizeof(V) / sizeof(E));
  if constexpr (n <= 2) {
    return n == 1 ? E(v[0]) : E(v[0] + v[1]);
  } else {
    typedef E H __attribute__((vector_size(sizeof(V) / 2)));
    H lo, hi;
    std::memcpy(&lo, &v, sizeof(H));
    std::memcpy(&hi, reinterpret_cast<const char*>(&v) + sizeof(H), sizeof(H));
    return hsum(lo + hi);
  }
}

// The lanes of a comparison result (lanes 0 or -1) as bits, lane i in bit i: one instruction or two on x86.
template <typename M>
inline uint32_t lane_bits(const M& m) {
#if defined(__AVX512F__)
  if constexpr (sizeof(M) == 64) {
    if constexpr (sizeof(m[0]) == 4) return _mm512_test_epi32_mask((__m512i)m, (__m512i)m);
    else return _mm512_test_epi64_mask((__m512i)m, (__m512i)m);
  }
#endif
#if defined(__AVX__)
  if constexpr (sizeof(M) == 32) {
    if constexpr (sizeof(m[0]) == 4) return _mm256_movemask_ps((__m256)m);
    else return _mm256_movemask_pd((__m256d)m);
  }
#endif
#if defined(__SSE2__)
  if constexpr (sizeof(M) == 16) {
    if constexpr (sizeof(m[0]) == 4) return _mm_movemask_ps((__m128)m);
    else return _mm_movemask_pd((__m128d)m);
  }
#endif
  uint32_t bits = 0;
  for (int i = 0; i < int(sizeof(M) / sizeof(m[0])); ++i) bits |= uint32_t(m[i] != 0) << i;
  return bits;
}

// a * b + c, fused where the target has FMA. Used inside the exp below (whose result is an approximation either
// way) and for the backward's gradient sums; the forward's compositing is never fused, so that it rounds like
// the PyTorch reference (see kernel_build.COMMON_CFLAGS).
template <typename V>
inline V fmadd(const V& a, const V& b, const V& c) {
  constexpr bool f32 = sizeof(a[0]) == 4;
#if defined(__AVX512F__)
  if constexpr (sizeof(V) == 64 && f32) return (V)_mm512_fmadd_ps((__m512)a, (__m512)b, (__m512)c);
  if constexpr (sizeof(V) == 64 && !f32) return (V)_mm512_fmadd_pd((__m512d)a, (__m512d)b, (__m512d)c);
#endif
#if defined(__FMA__)
  if constexpr (sizeof(V) == 32 && f32) return (V)_mm256_fmadd_ps((__m256)a, (__m256)b, (__m256)c);
  if constexpr (sizeof(V) == 32 && !f32) return (V)_mm256_fmadd_pd((__m256d)a, (__m256d)b, (__m256d)c);
  if constexpr (sizeof(V) == 16 && f32) return (V)_mm_fmadd_ps((__m128)a, (__m128)b, (__m128)c);
  if constexpr (sizeof(V) == 16 && !f32) return (V)_mm_fmadd_pd((__m128d)a, (__m128d)b, (__m128d)c);
#endif
  return a * b + c;
}

// exp on K vectors at once, of arguments clamped to [-87, 0] (the kernel uses exp only of powers <= 0; a lane
// with power > 0 is skipped, and the clamp keeps it finite; below -87 alpha is far under 1/255 anyway).
// float: x = k ln2 + r (Cody-Waite, |r| <= ln2 / 2), exp(r) by a degree-6 polynomial fitted for relative error
// (below 2^-28 on the interval; about 1 ulp in float with FMA, 1.5 without), times 2^k built in the exponent
// bits; 15 vector operations, branch-free. double (used by the tests): std::exp per lane. The K evaluations are
// written step by step side by side so that the CPU overlaps their dependency chains.
template <int K>
inline void vexp_n(const Simd<float>::V* x, Simd<float>::V* out) {
  using V = Simd<float>::V;
  using M = Simd<float>::M;
  const V lo = splat<V>(-87.0f), zero = splat<V>(0.0f);
  const V magic = splat<V>(12582912.0f);  // 1.5 * 2^23: t = x / ln2 + magic holds round(x / ln2) in its low bits
  const V nl2hi = splat<V>(-0.693145751953125f), nl2lo = splat<V>(-1.42860682030941723212e-6f);
  const V c6 = splat<V>(1.3843545610572375e-3f), c5 = splat<V>(8.374122275665495e-3f);
  const V c4 = splat<V>(4.166800189547691e-2f), c3 = splat<V>(1.6666431656098027e-1f);
  const V c2 = splat<V>(4.9999994217791327e-1f), one = splat<V>(1.0f);
  V xc[K], t[K], r[K], p[K];
  for (int j = 0; j < K; ++j) {
    xc[j] = x[j] < lo ? lo : x[j];
    xc[j] = xc[j] > zero ? zero : xc[j];
  }
#if defined(__AVX512F__) && defined(__AVX512VL__)
  // AVX-512: k rounded by vrndscaleps and 2^k applied by vscalefps, the same numbers in three fewer operations.
  constexpr bool avx512 = sizeof(V) == 32;
#else
  constexpr bool avx512 = false;
#endif
  V kf[K];
  for (int j = 0; j < K; ++j) {
    if constexpr (avx512) {
#if defined(__AVX512F__) && defined(__AVX512VL__)
      kf[j] = (V)_mm256_roundscale_ps((__m256)(xc[j] * 1.44269504088896341f),
                                      _MM_FROUND_TO_NEAREST_INT | _MM_FROUND_NO_EXC);
#endif
    } else {
      t[j] = xc[j] * 1.44269504088896341f + magic;
      kf[j] = t[j] - magic;
    }
  }
  for (int j = 0; j < K; ++j) r[j] = fmadd(kf[j], nl2hi, xc[j]);  // exact: k ln2hi has few bits
  for (int j = 0; j < K; ++j) r[j] = fmadd(kf[j], nl2lo, r[j]);
  for (int j = 0; j < K; ++j) p[j] = fmadd(c6, r[j], c5);
  for (int j = 0; j < K; ++j) p[j] = fmadd(p[j], r[j], c4);
  for (int j = 0; j < K; ++j) p[j] = fmadd(p[j], r[j], c3);
  for (int j = 0; j < K; ++j) p[j] = fmadd(p[j], r[j], c2);
  for (int j = 0; j < K; ++j) p[j] = fmadd(p[j], r[j], one);
  for (int j = 0; j < K; ++j) p[j] = fmadd(p[j], r[j], one);
  for (int j = 0; j < K; ++j) {
    if constexpr (avx512) {
#if defined(__AVX512F__) && defined(__AVX512VL__)
      out[j] = (V)_mm256_scalef_ps((__m256)p[j], (__m256)kf[j]);
#endif
    } else {
      const M bits = (reinterpret_cast<const M&>(t[j]) + (127 - 0x4B400000)) << 23;  // 2^k, k in [-126, 0]
      out[j] = p[j] * reinterpret_cast<const V&>(bits);
    }
  }
}
template <int K>
inline void vexp_n(const Simd<double>::V* x, Simd<double>::V* out) {
  for (int j = 0; j < K; ++j)
    for (int i = 0; i < Simd<double>::W; ++i) out[j][i] = std::exp(x[j][i] > 0.0 ? 0.0 : x[j][i]);
}

// exp of n vectors, four (then two, one) side by side.
template <typename V>
inline void vexp_all(const V* x, V* out, int n) {
  int j = 0;
  for (; j + 3 < n; j += 4) vexp_n<4>(x + j, out + j);
  if (j + 1 < n) vexp_n<2>(x + j, out + j), j += 2;
  if (j < n) vexp_n<1>(x + j, out + j);
}

// The vectors [c0, c1) of a tile row that hold the tile's pixel columns x0..x1-1.
template <int W>
inline void lane_span(int x0, int x1, int& c0, int& c1) {
  c0 = x0 / W;
  c1 = (x1 + W - 1) / W;
}

// The tiles, longest list first: handed out in that order (dynamic schedule), the threads finish together
// instead of one of them ending on a long tile.
inline std::vector<int> busiest_first(const int64_t* count, int n_tiles) {
  std::vector<int> order(n_tiles);
  std::iota(order.begin(), order.end(), 0);
  std::stable_sort(order.begin(), order.end(), [&](int a, int b) { return count[a] > count[b]; });
  return order;
}

// A tile's pixels as vectors: v = row * N + vector within the row, W lanes each.
// For one pair, the powers of the vectors in its reach box, and the list of those to evaluate: the vectors for
// which keep(v) (a scalar test: some pixel still composites there). Returns their number; pw[j] and idx[j] for j
// below it. (Testing the powers themselves against the 1/255 threshold, vector by vector, cost more than the
// exps and compositing it saved once the reach box is tight.)
template <typename T, typename Keep>
inline int candidates(const Gauss<T>& P, const Ref& R, const typename Simd<T>::V* xs, int py0, Keep keep,
                      typename Simd<T>::V* pw, int16_t* idx, typename Simd<T>::V* dx) {
  using V = typename Simd<T>::V;
  constexpr int W = Simd<T>::W, N = Simd<T>::N;
  int c0, c1;
  lane_span<W>(R.x0, R.x1, c0, c1);
  V cdx[N], bdx[N];
  for (int c = 0; c < N; ++c) dx[c] = xs[c] - P.mx;
  for (int c = c0; c < c1; ++c) {
    cdx[c] = P.ca * dx[c] * dx[c];
    bdx[c] = P.cb * dx[c];
  }
  int nv = 0;
  for (int r = R.y0; r < R.y1; ++r) {
    const T dy = T(py0 + r) - P.my;
    const T cdy = P.cc * dy * dy;
    for (int c = c0; c < c1; ++c) {
      // The reference's rounding: -0.5 (a dx dx + c dy dy) - b dx dy, products left to right.
      const int v = r * N + c;
      pw[nv] = T(-0.5) * (cdx[c] + cdy) - bdx[c] * dy;
      idx[nv] = static_cast<int16_t>(v);
      nv += keep(v);
    }
  }
  return nv;
}

template <typename T>
void forward_impl(const Gauss<T>* recs, const Ref* refs, const int64_t* tstart, const int64_t* tcount, const T* bg,
                  int width, int height, int threads, T* out_rgb, T* out_alpha, T* out_depth, T* out_T,
                  int32_t* out_last) {
  using V = typename Simd<T>::V;
  using M = typename Simd<T>::M;
  constexpr int W = Simd<T>::W, N = Simd<T>::N, NV = TILE * N;
  const int tw = (width + TILE - 1) / TILE, th = (height + TILE - 1) / TILE;
  const int n_tiles = tw * th;
  const V amax = splat<V>(Consts<T>::alpha_max), zero = splat<V>(0);
  const T amin = Consts<T>::alpha_min, tmin = Consts<T>::t_min;
  const std::vector<int> order = busiest_first(tcount, n_tiles);
#pragma omp parallel for schedule(dynamic, 1) num_threads(threads)
  for (int i = 0; i < n_tiles; ++i) {
    const int t = order[i];
    const int px0 = (t % tw) * TILE, py0 = (t / tw) * TILE;
    const int px1 = std::min(px0 + TILE, width), py1 = std::min(py0 + TILE, height);
    const int n_pix = (px1 - px0) * (py1 - py0);
    // Per pixel: transmittance (negated once the pixel has finished: a later Gaussian would take it below 1e-4;
    // pixels of a partial tile outside the image are born finished, at -1), accumulated r, g, b, depth, and
    // index+1 of the last composited Gaussian (as T: exact below 2^24 per tile, checked by the caller).
    V Tr[NV], ar[NV], ag[NV], ab[NV], az[NV], last[NV];
    V xs[N];
    for (int c = 0; c < N; ++c)
      for (int i = 0; i < W; ++i) xs[c][i] = T(px0 + c * W + i);
    for (int r = 0; r < TILE; ++r)
      for (int c = 0; c < N; ++c) {
        const int v = r * N + c;
        ar[v] = ag[v] = ab[v] = az[v] = last[v] = zero;
        for (int i = 0; i < W; ++i) Tr[v][i] = (px0 + c * W + i < px1 && py0 + r < py1) ? T(1) : T(-1);
      }
    // Per vector, the lanes (bits) of the pixels not finished; and the number of finished pixels.
    uint32_t live[NV];
    for (int v = 0; v < NV; ++v) live[v] = lane_bits(Tr[v] > T(0));
    int n_done = 0;
    V pw[NV], ex[NV], dx[N];
    int16_t idx[NV];
    const int64_t s = tstart[t], cnt = tcount[t];
    for (int64_t k = 0; k < cnt; ++k) {
      if (k + 4 < cnt) __builtin_prefetch(recs + refs[s + k + 4].k);
      const Ref& R = refs[s + k];
      const Gauss<T>& P = recs[R.k];
      const int nv = candidates<T>(P, R, xs, py0, [&](int v) { return live[v] != 0; }, pw, idx, dx);
      if (nv == 0) continue;
      vexp_all(pw, ex, nv);
      const T o = P.o, cr = P.cr, cg = P.cg, cbl = P.cbl, z = P.z;
      const V kk = splat<V>(k + 1);
      for (int j = 0; j < nv; ++j) {
        const int v = idx[j];
        V alpha = o * ex[j];
        alpha = alpha < amax ? alpha : amax;
        const V tr = Tr[v];
        const M ok = (tr > T(0)) & (pw[j] <= T(0)) & (alpha >= amin);
        const V next = tr * (T(1) - alpha);
        const M stop = ok & (next < tmin);
        const M use = ok & ~stop;
        const V w = use ? alpha * tr : zero;
        ar[v] += w * cr;
        ag[v] += w * cg;
        ab[v] += w * cbl;
        az[v] += w * z;
        Tr[v] = use ? next : (stop ? -tr : tr);
        last[v] = use ? kk : last[v];
        const uint32_t stopped = lane_bits(stop);
        live[v] &= ~stopped;
        n_done += __builtin_popcount(stopped);
      }
      if (n_done >= n_pix) break;
    }
    for (int y = py0; y < py1; ++y)
      for (int x = px0; x < px1; ++x) {
        const int v = (y - py0) * N + (x - px0) / W, i = (x - px0) % W;
        const int64_t q = static_cast<int64_t>(y) * width + x;
        const T tr = std::abs(Tr[v][i]);
        out_rgb[3 * q] = ar[v][i] + tr * bg[0];
        out_rgb[3 * q + 1] = ag[v][i] + tr * bg[1];
        out_rgb[3 * q + 2] = ab[v][i] + tr * bg[2];
        out_alpha[q] = T(1) - tr;
        out_depth[q] = az[v][i];
        out_T[q] = tr;
        out_last[q] = static_cast<int32_t>(last[v][i]);
      }
  }
}

// Backward: per pixel, walk the composited Gaussians back to front, recovering T before each one by division
// (1 - alpha >= 0.01). With B the normalised colour behind a Gaussian (r, g, b over the background, depth over
// 0, the alpha channel as colour 1 over 0), d out / d alpha_k = T_k (c_k - B_k) per channel; only its sum
// weighted by dL/d(out) is needed, so the pixel keeps the one number D = sum_ch G_ch B_ch, which follows B's
// update D <- D + alpha (Gc - D) with Gc = sum_ch G_ch c_ch. The conic and mean gradients are sums over the
// pixels of (polynomials in dx, dy) x d power: with dx fixed per lane and dy per row they are kept as per-lane
// sums of d power and dy d power and dy^2 d power, combined with dx once per pair.
template <typename T>
void backward_impl(const Gauss<T>* recs, const Ref* refs, const int64_t* tstart, const int64_t* tcount, const T* bg,
                   const T* final_T, const int32_t* last_in, const T* g_rgb, const T* g_alpha, const T* g_depth,
                   int width, int height, int threads, T* pair_grad) {
  using V = typename Simd<T>::V;
  using M = typename Simd<T>::M;
  constexpr int W = Simd<T>::W, N = Simd<T>::N, NV = TILE * N;
  const int tw = (width + TILE - 1) / TILE, th = (height + TILE - 1) / TILE;
  const int n_tiles = tw * th;
  const V amax = splat<V>(Consts<T>::alpha_max), zero = splat<V>(0);
  const T amin = Consts<T>::alpha_min;
  const std::vector<int> order = busiest_first(tcount, n_tiles);
#pragma omp parallel for schedule(dynamic, 1) num_threads(threads)
  for (int i = 0; i < n_tiles; ++i) {
    const int t = order[i];
    const int64_t s = tstart[t], cnt = tcount[t];
    if (cnt == 0) continue;
    const int px0 = (t % tw) * TILE, py0 = (t / tw) * TILE;
    const int px1 = std::min(px0 + TILE, width), py1 = std::min(py0 + TILE, height);
    // Per pixel: Tr = transmittance behind the Gaussians still to visit, D (above), G* = dL/d(output), last =
    // composited count (0 outside the image).
    V Tr[NV], D[NV], Gr[NV], Gg[NV], Gb[NV], Gz[NV], Ga[NV], last[NV];
    V xs[N];
    for (int c = 0; c < N; ++c)
      for (int i = 0; i < W; ++i) xs[c][i] = T(px0 + c * W + i);
    for (int v = 0; v < NV; ++v) {
      Tr[v] = splat<V>(1);
      D[v] = Gr[v] = Gg[v] = Gb[v] = Gz[v] = Ga[v] = last[v] = zero;
    }
    int32_t max_last = 0;
    for (int y = py0; y < py1; ++y)
      for (int x = px0; x < px1; ++x) {
        const int v = (y - py0) * N + (x - px0) / W, i = (x - px0) % W;
        const int64_t q = static_cast<int64_t>(y) * width + x;
        Tr[v][i] = final_T[q];
        last[v][i] = T(last_in[q]);
        max_last = std::max(max_last, last_in[q]);
        Gr[v][i] = g_rgb[3 * q], Gg[v][i] = g_rgb[3 * q + 1], Gb[v][i] = g_rgb[3 * q + 2];
        Gz[v][i] = g_depth[q], Ga[v][i] = g_alpha[q];
        D[v][i] = g_rgb[3 * q] * bg[0] + g_rgb[3 * q + 1] * bg[1] + g_rgb[3 * q + 2] * bg[2];
      }
    int32_t vlast[NV];  // per vector, the largest count
    for (int v = 0; v < NV; ++v) {
      vlast[v] = 0;
      for (int i = 0; i < W; ++i) vlast[v] = std::max(vlast[v], static_cast<int32_t>(last[v][i]));
    }
    for (int64_t k = max_last; k < cnt; ++k)  // behind every pixel's last Gaussian: no gradient
      for (int c = 0; c < NGRAD; ++c) pair_grad[(s + k) * NGRAD + c] = T(0);
    V pw[NV], ex[NV], dx[N];
    int16_t idx[NV];
    for (int64_t k = max_last - 1; k >= 0; --k) {
      if (k >= 4) __builtin_prefetch(recs + refs[s + k - 4].k);
      const Ref& R = refs[s + k];
      const Gauss<T>& P = recs[R.k];
      T* slot = pair_grad + (s + k) * NGRAD;
      const V kk = splat<V>(k);
      const int nv = candidates<T>(P, R, xs, py0, [&](int v) { return k < vlast[v]; }, pw, idx, dx);
      if (nv == 0) {
        for (int c = 0; c < NGRAD; ++c) slot[c] = T(0);
        continue;
      }
      vexp_all(pw, ex, nv);
      const T o = P.o, cr = P.cr, cg = P.cg, cbl = P.cbl, z = P.z;
      V d_o = zero, d_r = zero, d_g = zero, d_bl = zero, d_z = zero, s_yy = zero;
      const V vcg = splat<V>(cg), vcb = splat<V>(cbl), vz = splat<V>(z);
      V s_p[N], s_yp[N];  // per lane: sum of d power, of dy d power
      for (int c = 0; c < N; ++c) s_p[c] = s_yp[c] = zero;
      for (int j = 0; j < nv; ++j) {
        const int v = idx[j], c = v % N;
        const T dy = T(py0 + v / N) - P.my;
        const V raw = o * ex[j];
        const V alpha = raw < amax ? raw : amax;
        const M active = (kk < last[v]) & (pw[j] <= T(0)) & (alpha >= amin);
        const V t_k = Tr[v] / (T(1) - alpha);  // transmittance in front of this Gaussian
        const V w = active ? alpha * t_k : zero;
        d_r = fmadd(w, Gr[v], d_r);
        d_g = fmadd(w, Gg[v], d_g);
        d_bl = fmadd(w, Gb[v], d_bl);
        d_z = fmadd(w, Gz[v], d_z);
        const V gc = fmadd(Gz[v], vz, fmadd(Gb[v], vcb, fmadd(Gg[v], vcg, Gr[v] * cr)));
        const V diff = (gc + Ga[v]) - D[v];
        const V d_alpha = (active & (raw <= amax)) ? diff * t_k : zero;  // clamped alpha: no gradient
        D[v] = active ? fmadd(alpha, diff, D[v]) : D[v];
        Tr[v] = active ? t_k : Tr[v];
        d_o = fmadd(ex[j], d_alpha, d_o);
        const V d_pow = raw * d_alpha;
        s_p[c] += d_pow;
        s_yp[c] = fmadd(splat<V>(dy), d_pow, s_yp[c]);
        s_yy = fmadd(splat<V>(dy * dy), d_pow, s_yy);
      }
      // d power / d(mx, my, a, b, c) = (a dx + b dy, b dx + c dy, -dx^2 / 2, -dx dy, -dy^2 / 2).
      V sx = zero, sxx = zero, sy = zero, sxy = zero;
      for (int c = 0; c < N; ++c) {
        sx += dx[c] * s_p[c];
        sxx += dx[c] * dx[c] * s_p[c];
        sy += s_yp[c];
        sxy += dx[c] * s_yp[c];
      }
      const T Sx = hsum(sx), Sy = hsum(sy);
      slot[0] = P.ca * Sx + P.cb * Sy, slot[1] = P.cb * Sx + P.cc * Sy;
      slot[2] = T(-0.5) * hsum(sxx), slot[3] = -hsum(sxy), slot[4] = T(-0.5) * hsum(s_yy);
      slot[5] = hsum(d_o), slot[6] = hsum(d_r), slot[7] = hsum(d_g), slot[8] = hsum(d_bl), slot[9] = hsum(d_z);
    }
  }
}

// Sum the per-(tile, Gaussian) slots into per-Gaussian gradients: per record (parallel), its slots in tile order
// (deterministic whatever the threads), found through gpos.
template <typename T>
void sum_pairs(const T* pair_grad, const Gauss<T>* recs, const int32_t* gpos, int64_t nv, int threads, T* grad) {
#pragma omp parallel for schedule(static) num_threads(std::max(1, threads))
  for (int64_t k = 0; k < nv; ++k) {
    if (k + 4 < nv)
      for (int i = 0; i < std::min(recs[k + 4].npairs, 4); ++i)
        __builtin_prefetch(pair_grad + int64_t(gpos[recs[k + 4].first + i]) * NGRAD);
    T acc[NGRAD] = {};
    const int32_t* pos = gpos + recs[k].first;
    for (int i = 0; i < recs[k].npairs; ++i) {
      const T* p = pair_grad + int64_t(pos[i]) * NGRAD;
      for (int c = 0; c < NGRAD; ++c) acc[c] += p[c];
    }
    T* out = grad + int64_t(recs[k].g) * NGRAD;
    for (int c = 0; c < NGRAD; ++c) out[c] = acc[c];
  }
}

// ---------------------------------------------------------------------------------------------------------
// EWA projection, forward and hand-written backward (same formulas as worldtree/render/projection.py, which is
// the autograd oracle for it). One Gaussian per iteration, computed in double and stored in T.

struct Camera {
  double fx, fy, cx, cy, R[9], t[3], lxp, lxn, lyp, lyn;
  int width, height;
  double near, eps2d;
};

Camera make_camera(const at::Tensor& K, const at::Tensor& w2c, int64_t width, int64_t height, double near,
                   double eps2d) {
  auto k = K.to(at::kDouble).contiguous();
  auto v = w2c.to(at::kDouble).contiguous();
  const double* kp = k.data_ptr<double>();
  const double* vp = v.data_ptr<double>();
  Camera c;
  c.fx = kp[0], c.fy = kp[4], c.cx = kp[2], c.cy = kp[5];
  for (int r = 0; r < 3; ++r) {
    for (int j = 0; j < 3; ++j) c.R[3 * r + j] = vp[4 * r + j];
    c.t[r] = vp[4 * r + 3];
  }
  c.width = int(width), c.height = int(height), c.near = near, c.eps2d = eps2d;
  const double tan_x = 0.5 * width / c.fx, tan_y = 0.5 * height / c.fy;
  c.lxp = (width - 0.5 - c.cx) / c.fx + 0.3 * tan_x;
  c.lxn = (c.cx + 0.5) / c.fx + 0.3 * tan_x;
  c.lyp = (height - 0.5 - c.cy) / c.fy + 0.3 * tan_y;
  c.lyn = (c.cy + 0.5) / c.fy + 0.3 * tan_y;
  return c;
}

// The projection runs PL Gaussians at once, one per lane of a vector of doubles (4 with AVX, 2 with SSE2): every
// lane does exactly the operations of the one-Gaussian formula in the same order (nothing is fused), so the
// results are those of one Gaussian at a time, and a lane culled early computes on regardless (its results
// are not used).
constexpr int PL = VBYTES / int(sizeof(double));
typedef double DV __attribute__((vector_size(PL * sizeof(double))));
typedef int64_t DM __attribute__((vector_size(PL * sizeof(double))));

inline DV bc(double x) { return splat<DV>(x); }
inline DM finite(const DV& x) { return (x - x) == 0.0; }             // std::isfinite, lane by lane
inline DV sel(const DM& m, const DV& a, const DV& b) { return m ? a : b; }
inline DV vmax(const DV& a, const DV& b) { return a < b ? b : a; }  // std::max(a, b), lane by lane
inline DV vmin(const DV& a, const DV& b) { return b < a ? b : a; }  // std::min(a, b), lane by lane
inline DV vsqrt(const DV& x) {  // correctly rounded, like std::sqrt
#if defined(__AVX__)
  return (DV)_mm256_sqrt_pd((__m256d)x);  // VBYTES = 32: PL = 4
#elif defined(__SSE2__)
  return (DV)_mm_sqrt_pd((__m128d)x);  // PL = 2
#else
  DV r = x;
  for (int i = 0; i < PL; ++i) r[i] = std::sqrt(x[i]);
  return r;
#endif
}
inline DV vexp(const DV& x) {
  DV r = x;
  for (int i = 0; i < PL; ++i) r[i] = std::exp(x[i]);
  return r;
}

// Everything the forward computes for a Gaussian (a lane), kept for its backward.
struct ProjState {
  DV m[3], qn, qh[4], s[3], Rq[9], M[9], p[3], rz, X, Y, xin, yin, W[9], A0[3], A1[3], a, b, c, det;
  DV C[3];  // A0 x A1, from the scaled minors (accurate where the rows are nearly parallel)
};

// Returns the lanes whose Gaussian is not culled before its covariance is known to be usable.
inline DM project_one(const Camera& cam, const DV* m, const DV* q, const DV* ls, ProjState& S) {
  DM ok = finite(m[0]) & finite(m[1]) & finite(m[2]) & finite(ls[0]) & finite(ls[1]) & finite(ls[2]);
  ok &= finite(q[0]) & finite(q[1]) & finite(q[2]) & finite(q[3]);
  S.qn = vsqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3]);
  ok &= S.qn > 1e-8;
  for (int i = 0; i < 3; ++i) S.m[i] = m[i];
  for (int r = 0; r < 3; ++r)
    S.p[r] = cam.R[3 * r] * m[0] + cam.R[3 * r + 1] * m[1] + cam.R[3 * r + 2] * m[2] + cam.t[r];
  ok &= finite(S.p[0]) & finite(S.p[1]) & finite(S.p[2]) & (S.p[2] > cam.near);
  const DV iqn = 1.0 / S.qn;
  for (int i = 0; i < 4; ++i) S.qh[i] = q[i] * iqn;
  const DV w = S.qh[0], x = S.qh[1], y = S.qh[2], z = S.qh[3];
  const DV Rq[9] = {1 - 2 * (y * y + z * z), 2 * (x * y - w * z),     2 * (x * z + w * y),
                    2 * (x * y + w * z),     1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
                    2 * (x * z - w * y),     2 * (y * z + w * x),     1 - 2 * (x * x + y * y)};
  for (int i = 0; i < 3; ++i) S.s[i] = vexp(ls[i]);
  for (int j = 0; j < 3; ++j)
    for (int k = 0; k < 3; ++k) {
      S.Rq[3 * j + k] = Rq[3 * j + k];
      S.M[3 * j + k] = Rq[3 * j + k] * S.s[k];
    }
  // Bq = R Rq, so W = R M = Bq diag(s); B = J Bq and A = J W = B diag(s). B also gives the determinant below.
  DV Bq[9];
  for (int r = 0; r < 3; ++r)
    for (int k = 0; k < 3; ++k) {
      Bq[3 * r + k] = cam.R[3 * r] * Rq[k] + cam.R[3 * r + 1] * Rq[3 + k] + cam.R[3 * r + 2] * Rq[6 + k];
      S.W[3 * r + k] = Bq[3 * r + k] * S.s[k];
    }
  S.rz = 1.0 / S.p[2];
  const DV xr = S.p[0] * S.rz, yr = S.p[1] * S.rz;
  S.X = vmin(vmax(xr, bc(-cam.lxn)), bc(cam.lxp));
  S.Y = vmin(vmax(yr, bc(-cam.lyn)), bc(cam.lyp));
  S.xin = sel((xr > -cam.lxn) & (xr < cam.lxp), bc(1.0), bc(0.0));  // direction not clamped: J follows x
  S.yin = sel((yr > -cam.lyn) & (yr < cam.lyp), bc(1.0), bc(0.0));
  const DV j00 = cam.fx * S.rz, j02 = -cam.fx * S.X * S.rz, j11 = cam.fy * S.rz, j12 = -cam.fy * S.Y * S.rz;
  DV B0[3], B1[3];
  for (int k = 0; k < 3; ++k) {
    B0[k] = j00 * Bq[k] + j02 * Bq[6 + k];
    B1[k] = j11 * Bq[3 + k] + j12 * Bq[6 + k];
    S.A0[k] = B0[k] * S.s[k];
    S.A1[k] = B1[k] * S.s[k];
  }
  const DV sq0 = S.A0[0] * S.A0[0] + S.A0[1] * S.A0[1] + S.A0[2] * S.A0[2];
  const DV sq1 = S.A1[0] * S.A1[0] + S.A1[1] * S.A1[1] + S.A1[2] * S.A1[2];
  S.a = sq0 + cam.eps2d;
  S.b = S.A0[0] * S.A1[0] + S.A0[1] * S.A1[1] + S.A0[2] * S.A1[2];
  S.c = sq1 + cam.eps2d;
  // det = a c - b^2, written without its cancellation (which leaves only rounding noise, of either sign, for
  // large thin footprints): by Cauchy-Binet det(A A^T) is the sum over column pairs of
  // (s_i s_j minor_ij(B))^2, and the eps2d terms are positive. Same as projection.py.
  const DV t01 = S.s[0] * S.s[1] * (B0[0] * B1[1] - B0[1] * B1[0]);
  const DV t02 = S.s[0] * S.s[2] * (B0[0] * B1[2] - B0[2] * B1[0]);
  const DV t12 = S.s[1] * S.s[2] * (B0[1] * B1[2] - B0[2] * B1[1]);
  S.det = t01 * t01 + t02 * t02 + t12 * t12 + cam.eps2d * (sq0 + sq1) + cam.eps2d * cam.eps2d;
  S.C[0] = t12, S.C[1] = -t02, S.C[2] = t01;
  ok &= finite(S.a) & finite(S.b) & finite(S.c) & finite(S.det) & (S.det > 0) & finite(S.c / S.det) &
        finite(S.a / S.det);
  return ok;
}

// The lanes of Gaussians i0 .. i0 + PL - 1 (those below n and with use(i)); the others get harmless inputs.
template <typename T, typename Use>
inline void load_lanes(const T* means, const T* quats, const T* lsc, int64_t i0, int64_t n, Use use, DV* m, DV* q,
                       DV* ls, bool* live) {
  for (int L = 0; L < PL; ++L) {
    const int64_t i = i0 + L;
    live[L] = i < n && use(i);
    for (int k = 0; k < 3; ++k) m[k][L] = live[L] ? double(means[3 * i + k]) : 0.0;
    for (int k = 0; k < 4; ++k) q[k][L] = live[L] ? double(quats[4 * i + k]) : (k == 0 ? 1.0 : 0.0);
    for (int k = 0; k < 3; ++k) ls[k][L] = live[L] ? double(lsc[3 * i + k]) : 0.0;
  }
}

template <typename T>
void project_forward_impl(const Camera& cam, const T* means, const T* quats, const T* lsc, const bool* keep, int64_t n,
                          int threads, T* means2d, T* conics, T* depths, int32_t* radii) {
  const int tw = (cam.width + TILE - 1) / TILE, th = (cam.height + TILE - 1) / TILE;
#pragma omp parallel for schedule(static) num_threads(threads)
  for (int64_t i0 = 0; i0 < n; i0 += PL) {
    DV m[3], q[4], ls[3];
    bool live[PL];
    load_lanes<T>(means, quats, lsc, i0, n, [&](int64_t i) { return keep[i]; }, m, q, ls, live);
    ProjState S;
    const DM ok = project_one(cam, m, q, ls, S);
    for (int L = 0; L < PL && i0 + L < n; ++L) {
      const int64_t i = i0 + L;
      means2d[2 * i] = means2d[2 * i + 1] = T(0);
      conics[3 * i] = conics[3 * i + 1] = conics[3 * i + 2] = T(0);
      depths[i] = T(0);
      radii[i] = 0;
      if (!live[L] || !ok[L]) continue;
      const double a = S.a[L], b = S.b[L], c = S.c[L], det = S.det[L];
      {
        // Cull what the storage type cannot hold, as the PyTorch projection does in that dtype: a covariance or
        // determinant that overflows, or a conic that is not finite and positive on its diagonal.
        const T ta = T(a), tc = T(c), tdet = T(det);
        const T c0 = T(c / det), c1 = T(-b / det), c2 = T(a / det);
        if (!(std::isfinite(double(tdet)) && tdet > T(0) && std::isfinite(double(ta)) && std::isfinite(double(tc))))
          continue;
        if (!(std::isfinite(double(c0)) && std::isfinite(double(c1)) && std::isfinite(double(c2)) && c0 > T(0) &&
              c2 > T(0)))
          continue;
      }
      const double mid = 0.5 * (a + c);
      double r = std::ceil(3.0 * std::sqrt(mid + std::sqrt(std::max(mid * mid - det, 0.1))));
      r = std::min(r, double(1 << 24));
      if (!(r > 0)) continue;
      const double rz = S.rz[L];
      const T u = T(cam.fx * S.p[0][L] * rz + cam.cx), v = T(cam.fy * S.p[1][L] * rz + cam.cy);
      if (!std::isfinite(double(u)) || !std::isfinite(double(v))) continue;
      int x0, x1, y0, y1;
      tile_rect<T>(u, v, T(r), tw, th, x0, x1, y0, y1);
      if (!(x1 > x0 && y1 > y0)) continue;
      means2d[2 * i] = u, means2d[2 * i + 1] = v;
      conics[3 * i] = T(c / det), conics[3 * i + 1] = T(-b / det), conics[3 * i + 2] = T(a / det);
      depths[i] = T(S.p[2][L]);
      radii[i] = static_cast<int32_t>(r);
    }
  }
}

template <typename T>
void project_backward_impl(const Camera& cam, const T* means, const T* quats, const T* lsc, const int32_t* radii,
                           int64_t n, const T* g_m2d, const T* g_con, const T* g_z, int threads, T* d_means,
                           T* d_quats, T* d_ls, double* d_Rt /* [n][12], summed by the caller in order */) {
#pragma omp parallel for schedule(static) num_threads(threads)
  for (int64_t i0 = 0; i0 < n; i0 += PL) {
    DV m[3], q[4], ls[3];
    bool live[PL];
    load_lanes<T>(means, quats, lsc, i0, n, [&](int64_t i) { return radii[i] > 0; }, m, q, ls, live);
    for (int L = 0; L < PL && i0 + L < n; ++L) {
      const int64_t i = i0 + L;
      for (int k = 0; k < 3; ++k) d_means[3 * i + k] = d_ls[3 * i + k] = T(0);
      for (int k = 0; k < 4; ++k) d_quats[4 * i + k] = T(0);
    }
    if (std::none_of(live, live + PL, [](bool b) { return b; })) continue;
    ProjState S;
    const DM ok = project_one(cam, m, q, ls, S);
    DV gu, gv, gz, g0, g1, g2;
    for (int L = 0; L < PL; ++L) {
      const int64_t i = live[L] ? i0 + L : -1;
      gu[L] = i >= 0 ? double(g_m2d[2 * i]) : 0.0, gv[L] = i >= 0 ? double(g_m2d[2 * i + 1]) : 0.0;
      gz[L] = i >= 0 ? double(g_z[i]) : 0.0;
      g0[L] = i >= 0 ? double(g_con[3 * i]) : 0.0, g1[L] = i >= 0 ? double(g_con[3 * i + 1]) : 0.0;
      g2[L] = i >= 0 ? double(g_con[3 * i + 2]) : 0.0;
    }
    const DV a = S.a, b = S.b, c = S.c, det = S.det, d2 = det * det;
    // conic = (c, -b, a) / det. The numerators go through a, b, c; det through its own gradient,
    // d det / dA0 = 2 (A1 x C + eps A0), d det / dA1 = 2 (C x A0 + eps A1) with C = A0 x A1: going through
    // d(a c - b^2) instead would cancel huge terms for long thin footprints (as the forward would).
    const DV idet = 1.0 / det;
    const DV ga = g2 * idet, gb = -g1 * idet, gc = g0 * idet;
    const DV gdet = -(g0 * c - g1 * b + g2 * a) / d2;
    const DV* A0 = S.A0;
    const DV* A1 = S.A1;
    const DV* C = S.C;
    const DV A1xC[3] = {A1[1] * C[2] - A1[2] * C[1], A1[2] * C[0] - A1[0] * C[2], A1[0] * C[1] - A1[1] * C[0]};
    const DV CxA0[3] = {C[1] * A0[2] - C[2] * A0[1], C[2] * A0[0] - C[0] * A0[2], C[0] * A0[1] - C[1] * A0[0]};
    DV dA0[3], dA1[3];
    for (int k = 0; k < 3; ++k) {
      dA0[k] = 2 * ga * A0[k] + gb * A1[k] + 2 * gdet * (A1xC[k] + cam.eps2d * A0[k]);
      dA1[k] = gb * A0[k] + 2 * gc * A1[k] + 2 * gdet * (CxA0[k] + cam.eps2d * A1[k]);
    }
    const DV rz = S.rz;
    const double fx = cam.fx, fy = cam.fy;
    const DV j00 = fx * rz, j02 = -fx * S.X * rz, j11 = fy * rz, j12 = -fy * S.Y * rz;
    DV dW[9];
    DV dj00 = bc(0), dj02 = bc(0), dj11 = bc(0), dj12 = bc(0);
    for (int k = 0; k < 3; ++k) {
      dW[k] = j00 * dA0[k];
      dW[3 + k] = j11 * dA1[k];
      dW[6 + k] = j02 * dA0[k] + j12 * dA1[k];
      dj00 += dA0[k] * S.W[k];
      dj02 += dA0[k] * S.W[6 + k];
      dj11 += dA1[k] * S.W[3 + k];
      dj12 += dA1[k] * S.W[6 + k];
    }
    // W = R M.
    DV dR[9], dM[9];
    for (int r = 0; r < 3; ++r)
      for (int j = 0; j < 3; ++j)
        dR[3 * r + j] = dW[3 * r] * S.M[3 * j] + dW[3 * r + 1] * S.M[3 * j + 1] + dW[3 * r + 2] * S.M[3 * j + 2];
    for (int j = 0; j < 3; ++j)
      for (int k = 0; k < 3; ++k)
        dM[3 * j + k] = cam.R[j] * dW[k] + cam.R[3 + j] * dW[3 + k] + cam.R[6 + j] * dW[6 + k];
    // M = Rq diag(s), s = exp(log_scales).
    DV dRq[9], dls[3];
    for (int k = 0; k < 3; ++k) {
      DV ds = bc(0);
      for (int j = 0; j < 3; ++j) {
        dRq[3 * j + k] = dM[3 * j + k] * S.s[k];
        ds += dM[3 * j + k] * S.Rq[3 * j + k];
      }
      dls[k] = ds * S.s[k];
    }
    const DV w = S.qh[0], x = S.qh[1], y = S.qh[2], z = S.qh[3];
    const DV* G = dRq;
    const DV dqh[4] = {
        2 * (-z * G[1] + y * G[2] + z * G[3] - x * G[5] - y * G[6] + x * G[7]),
        2 * (y * G[1] + z * G[2] + y * G[3] - 2 * x * G[4] - w * G[5] + z * G[6] + w * G[7] - 2 * x * G[8]),
        2 * (-2 * y * G[0] + x * G[1] + w * G[2] + x * G[3] + z * G[5] - w * G[6] + z * G[7] - 2 * y * G[8]),
        2 * (-2 * z * G[0] - w * G[1] + x * G[2] + w * G[3] - 2 * z * G[4] + y * G[5] + x * G[6] + y * G[7])};
    const DV dot = dqh[0] * S.qh[0] + dqh[1] * S.qh[1] + dqh[2] * S.qh[2] + dqh[3] * S.qh[3];
    const DV iqn = 1.0 / S.qn;
    DV dq[4];
    for (int k = 0; k < 4; ++k) dq[k] = (dqh[k] - S.qh[k] * dot) * iqn;
    // Camera point p: from the 2D mean, the depth and the Jacobian entries.
    const DV px = S.p[0], py = S.p[1];
    DV dp[3];
    dp[0] = gu * fx * rz - dj02 * fx * rz * S.xin * rz;
    dp[1] = gv * fy * rz - dj12 * fy * rz * S.yin * rz;
    dp[2] = gz - gu * fx * px * rz * rz - gv * fy * py * rz * rz - dj00 * fx * rz * rz - dj11 * fy * rz * rz -
            dj02 * fx * (S.xin * (-px * rz * rz) * rz - S.X * rz * rz) -
            dj12 * fy * (S.yin * (-py * rz * rz) * rz - S.Y * rz * rz);
    // p = R m + t.
    DV dmean[3];
    for (int j = 0; j < 3; ++j) dmean[j] = cam.R[j] * dp[0] + cam.R[3 + j] * dp[1] + cam.R[6 + j] * dp[2];
    for (int L = 0; L < PL; ++L) {
      if (!live[L] || !ok[L]) continue;  // culled: exactly zero gradient
      const int64_t i = i0 + L;
      for (int k = 0; k < 3; ++k) d_ls[3 * i + k] = T(dls[k][L]);
      for (int k = 0; k < 4; ++k) d_quats[4 * i + k] = T(dq[k][L]);
      for (int j = 0; j < 3; ++j) d_means[3 * i + j] = T(dmean[j][L]);
      double* acc = d_Rt + 12 * i;
      for (int r = 0; r < 3; ++r) {
        for (int j = 0; j < 3; ++j) acc[3 * r + j] += dR[3 * r + j][L] + dp[r][L] * S.m[j][L];
        acc[9 + r] += dp[r][L];
      }
    }
  }
}

void check(const at::Tensor& t, const char* name, int64_t n, int64_t cols) {
  TORCH_CHECK(t.device().is_cpu(), name, " must be a CPU tensor");
  TORCH_CHECK(t.is_contiguous(), name, " must be contiguous");
  TORCH_CHECK(t.size(0) == n, name, " has the wrong length");
  if (cols > 0) TORCH_CHECK(t.dim() == 2 && t.size(1) == cols, name, " has the wrong shape");
}

}  // namespace

// Returns rgb [H,W,3], alpha [H,W], depth [H,W], final_T [H,W], last [H,W] int32, ids [M] int32,
// tile_start [n_tiles] int64, tile_count [n_tiles] int64, and what the backward reads besides: recs
// [visible * record size] uint8 (the Gaussian records, depth order), refs [M] int64 (the packed pairs) and
// gpos [M] int32 (the pairs grouped by Gaussian).
std::vector<at::Tensor> rasterize_forward(at::Tensor means2d, at::Tensor conics, at::Tensor opac, at::Tensor colors,
                                          at::Tensor depths, at::Tensor radii, at::Tensor bg, int64_t width,
                                          int64_t height, int64_t threads) {
  const int64_t n = means2d.size(0);
  check(means2d, "means2d", n, 2);
  check(conics, "conics", n, 3);
  check(opac, "opacities", n, 0);
  check(colors, "colors", n, 3);
  check(depths, "depths", n, 0);
  check(radii, "radii", n, 0);
  TORCH_CHECK(radii.scalar_type() == at::kInt, "radii must be int32");
  TORCH_CHECK(bg.is_contiguous() && bg.numel() == 3, "background must be 3 contiguous values");
  auto opts = means2d.options();
  auto rgb = at::empty({height, width, 3}, opts);
  auto alpha = at::empty({height, width}, opts);
  auto depth = at::empty({height, width}, opts);
  auto final_T = at::empty({height, width}, opts);
  auto last = at::empty({height, width}, opts.dtype(at::kInt));
  at::Tensor ids, tstart, tcount, recs, refs, gpos;
  AT_DISPATCH_FLOATING_TYPES(means2d.scalar_type(), "rasterize_forward", [&] {
    Bins<scalar_t> bins = bin_gaussians<scalar_t>(
        means2d.data_ptr<scalar_t>(), conics.data_ptr<scalar_t>(), opac.data_ptr<scalar_t>(),
        colors.data_ptr<scalar_t>(), depths.data_ptr<scalar_t>(), radii.data_ptr<int32_t>(), n, int(width),
        int(height), int(threads));
    for (int64_t c : bins.count)
      TORCH_CHECK(c < (int64_t(1) << 24), "more than 2^24 Gaussians in one tile; use the reference backend");
    const int64_t nt = static_cast<int64_t>(bins.start.size());
    tstart = at::empty({nt}, opts.dtype(at::kLong));
    tcount = at::empty({nt}, opts.dtype(at::kLong));
    std::copy(bins.start.begin(), bins.start.end(), tstart.data_ptr<int64_t>());
    std::copy(bins.count.begin(), bins.count.end(), tcount.data_ptr<int64_t>());
    ids = bins.ids, recs = bins.recs, refs = bins.refs, gpos = bins.gpos;
    forward_impl<scalar_t>(reinterpret_cast<const Gauss<scalar_t>*>(recs.data_ptr<uint8_t>()),
                           reinterpret_cast<const Ref*>(refs.data_ptr<int64_t>()), tstart.data_ptr<int64_t>(),
                           tcount.data_ptr<int64_t>(), bg.data_ptr<scalar_t>(), int(width), int(height),
                           int(threads), rgb.data_ptr<scalar_t>(), alpha.data_ptr<scalar_t>(),
                           depth.data_ptr<scalar_t>(), final_T.data_ptr<scalar_t>(), last.data_ptr<int32_t>());
  });
  return {rgb, alpha, depth, final_T, last, ids, tstart, tcount, recs, refs, gpos};
}

// Returns gradients: means2d [N,2], conics [N,3], opacities [N], colors [N,3], depths [N]; n = N, and the other
// tensors as the forward returned them (recs, refs, gpos, tile_start, tile_count, final_T, last) or was passed
// them (bg).
std::vector<at::Tensor> rasterize_backward(at::Tensor recs, at::Tensor refs, at::Tensor gpos, at::Tensor tstart,
                                           at::Tensor tcount, at::Tensor bg, at::Tensor final_T, at::Tensor last,
                                           at::Tensor g_rgb, at::Tensor g_alpha, at::Tensor g_depth, int64_t n,
                                           int64_t width, int64_t height, int64_t threads) {
  const int64_t tw = (width + TILE - 1) / TILE, th = (height + TILE - 1) / TILE, nt = tw * th;
  TORCH_CHECK(g_rgb.is_contiguous() && g_alpha.is_contiguous() && g_depth.is_contiguous(),
              "output gradients must be contiguous");
  TORCH_CHECK(g_rgb.numel() == 3 * width * height && g_alpha.numel() == width * height &&
                  g_depth.numel() == width * height,
              "output gradients have the wrong size");
  TORCH_CHECK(final_T.is_contiguous() && final_T.numel() == width * height, "final_T has the wrong size");
  TORCH_CHECK(last.is_contiguous() && last.scalar_type() == at::kInt && last.numel() == width * height,
              "last must be the [H, W] int32 tensor the forward returned");
  TORCH_CHECK(bg.is_contiguous() && bg.numel() == 3, "background must be 3 contiguous values");
  TORCH_CHECK(tstart.is_contiguous() && tcount.is_contiguous() && tstart.scalar_type() == at::kLong &&
                  tcount.scalar_type() == at::kLong && tstart.numel() == nt && tcount.numel() == nt,
              "tile_start / tile_count must be the int64 tensors the forward returned");
  TORCH_CHECK(recs.is_contiguous() && recs.scalar_type() == at::kByte, "recs must be the forward's uint8 tensor");
  TORCH_CHECK(refs.is_contiguous() && refs.scalar_type() == at::kLong, "refs must be the forward's int64 tensor");
  const int64_t m = refs.numel();
  TORCH_CHECK(gpos.is_contiguous() && gpos.scalar_type() == at::kInt && gpos.numel() == m,
              "gpos must be the forward's int32 tensor, one per pair");
  auto opts = final_T.options();
  auto grad = at::zeros({n, NGRAD}, opts);
  AT_DISPATCH_FLOATING_TYPES(final_T.scalar_type(), "rasterize_backward", [&] {
    using G = Gauss<scalar_t>;
    TORCH_CHECK(recs.numel() % int64_t(sizeof(G)) == 0, "recs does not hold whole records of this dtype");
    const int64_t nv = recs.numel() / int64_t(sizeof(G));
    const G* rec = reinterpret_cast<const G*>(recs.data_ptr<uint8_t>());
    const Ref* ref = reinterpret_cast<const Ref*>(refs.data_ptr<int64_t>());
    const int64_t* st = tstart.data_ptr<int64_t>();
    const int64_t* ct = tcount.data_ptr<int64_t>();
    for (int64_t t = 0; t < nt; ++t)
      TORCH_CHECK(st[t] >= 0 && ct[t] >= 0 && st[t] + ct[t] <= m, "tile lists outside the pairs");
    const int32_t* pos = gpos.data_ptr<int32_t>();
    for (int64_t j = 0; j < m; ++j)
      TORCH_CHECK(pos[j] >= 0 && pos[j] < m && ref[j].k >= 0 && ref[j].k < nv && ref[j].x1 <= TILE &&
                      ref[j].y1 <= TILE,
                  "pairs outside the records");
    int64_t slots = 0;
    for (int64_t k = 0; k < nv; ++k) {
      TORCH_CHECK(rec[k].g >= 0 && rec[k].g < n && rec[k].first == slots && rec[k].npairs >= 0,
                  "records do not match these Gaussians");
      slots += rec[k].npairs;
    }
    TORCH_CHECK(slots == m, "records and pairs do not match");
    // Every slot of a listed pair is written (zeros where no pixel composites it).
    auto pair_grad = at::empty({m, NGRAD}, opts);
    scalar_t* pg = pair_grad.data_ptr<scalar_t>();
    backward_impl<scalar_t>(rec, ref, st, ct, bg.data_ptr<scalar_t>(), final_T.data_ptr<scalar_t>(),
                            last.data_ptr<int32_t>(), g_rgb.data_ptr<scalar_t>(), g_alpha.data_ptr<scalar_t>(),
                            g_depth.data_ptr<scalar_t>(), int(width), int(height), int(threads), pg);
    sum_pairs<scalar_t>(pg, rec, pos, nv, int(threads), grad.data_ptr<scalar_t>());
  });
  return {grad.narrow(1, 0, 2), grad.narrow(1, 2, 3), grad.select(1, 5), grad.narrow(1, 6, 3), grad.select(1, 9)};
}

// Returns means2d [N,2], conics [N,3], depths [N], radii [N] int32 (zeros where culled).
std::vector<at::Tensor> project_forward(at::Tensor means, at::Tensor quats, at::Tensor log_scales, at::Tensor K,
                                        at::Tensor w2c, at::Tensor keep, int64_t width, int64_t height, double near,
                                        double eps2d, int64_t threads) {
  const int64_t n = means.size(0);
  check(means, "means", n, 3);
  check(quats, "quats", n, 4);
  check(log_scales, "log_scales", n, 3);
  check(keep, "keep", n, 0);
  TORCH_CHECK(keep.scalar_type() == at::kBool, "keep must be bool");
  const Camera cam = make_camera(K, w2c, width, height, near, eps2d);
  auto opts = means.options();
  auto means2d = at::empty({n, 2}, opts), conics = at::empty({n, 3}, opts), depths = at::empty({n}, opts);
  auto radii = at::empty({n}, opts.dtype(at::kInt));
  AT_DISPATCH_FLOATING_TYPES(means.scalar_type(), "project_forward", [&] {
    project_forward_impl<scalar_t>(cam, means.data_ptr<scalar_t>(), quats.data_ptr<scalar_t>(),
                                   log_scales.data_ptr<scalar_t>(), keep.data_ptr<bool>(), n, int(threads),
                                   means2d.data_ptr<scalar_t>(), conics.data_ptr<scalar_t>(),
                                   depths.data_ptr<scalar_t>(), radii.data_ptr<int32_t>());
  });
  return {means2d, conics, depths, radii};
}

// Returns gradients: means [N,3], quats [N,4], log_scales [N,3], w2c [4,4] (rotation and translation rows).
std::vector<at::Tensor> project_backward(at::Tensor means, at::Tensor quats, at::Tensor log_scales, at::Tensor K,
                                         at::Tensor w2c, at::Tensor radii, at::Tensor g_m2d, at::Tensor g_con,
                                         at::Tensor g_z, int64_t width, int64_t height, double near, double eps2d,
                                         int64_t threads) {
  const int64_t n = means.size(0);
  check(g_m2d, "grad means2d", n, 2);
  check(g_con, "grad conics", n, 3);
  check(g_z, "grad depths", n, 0);
  const Camera cam = make_camera(K, w2c, width, height, near, eps2d);
  auto opts = means.options();
  auto d_means = at::empty({n, 3}, opts), d_quats = at::empty({n, 4}, opts);
  auto d_ls = at::empty({n, 3}, opts);
  const int nt = std::max<int>(1, int(threads));
  // Per-Gaussian pose contributions, summed serially below so the result does not depend on the threads.
  auto d_Rt = at::zeros({n, 12}, opts.dtype(at::kDouble));
  AT_DISPATCH_FLOATING_TYPES(means.scalar_type(), "project_backward", [&] {
    project_backward_impl<scalar_t>(cam, means.data_ptr<scalar_t>(), quats.data_ptr<scalar_t>(),
                                    log_scales.data_ptr<scalar_t>(), radii.data_ptr<int32_t>(), n,
                                    g_m2d.data_ptr<scalar_t>(), g_con.data_ptr<scalar_t>(), g_z.data_ptr<scalar_t>(),
                                    nt, d_means.data_ptr<scalar_t>(), d_quats.data_ptr<scalar_t>(),
                                    d_ls.data_ptr<scalar_t>(), d_Rt.data_ptr<double>());
  });
  auto rt = at::zeros({12}, opts.dtype(at::kDouble));
  {
    const double* src = d_Rt.data_ptr<double>();
    double* dst = rt.data_ptr<double>();
    for (int64_t i = 0; i < n; ++i)
      for (int k = 0; k < 12; ++k) dst[k] += src[12 * i + k];
  }
  auto d_w2c = at::zeros({4, 4}, opts.dtype(at::kDouble));
  d_w2c.narrow(0, 0, 3).narrow(1, 0, 3).copy_(rt.narrow(0, 0, 9).reshape({3, 3}));
  d_w2c.narrow(0, 0, 3).select(1, 3).copy_(rt.narrow(0, 9, 3));
  return {d_means, d_quats, d_ls, d_w2c.to(w2c.scalar_type())};
}

// The op namespace is the build's name (torch passes -DTORCH_EXTENSION_NAME=<name>), unique per build, so that
// several targets can be loaded in one process. The extra macro level expands TORCH_EXTENSION_NAME before
// TORCH_LIBRARY pastes it into identifiers. Schemas are inferred from the signatures (int64_t -> int, double ->
// float, std::vector<Tensor> -> Tensor[]); the kernels are registered for every backend, as the pybind11 functions
// were, and check themselves that their tensors are on the CPU.
#define WORLDTREE_LIBRARY(ns, m) TORCH_LIBRARY(ns, m)
WORLDTREE_LIBRARY(TORCH_EXTENSION_NAME, m) {
  m.def("project_forward", &project_forward);    // EWA projection forward (CPU)
  m.def("project_backward", &project_backward);  // EWA projection backward (CPU)
  m.def("forward", &rasterize_forward);          // Gaussian tile rasterizer forward (CPU)
  m.def("backward", &rasterize_backward);        // Gaussian tile rasterizer backward (CPU)
}
