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
// Backward: per pixel, walk the composited Gaussians back to front, recovering T before each one by division
// (1 - alpha >= 0.01) and keeping B, the normalised colour behind it, so that d out / d alpha_k = T_k (c_k - B_k)
// for every channel (r, g, b over the background, depth over 0, and the alpha channel as colour 1 over 0).
// Each (tile, Gaussian) pair owns a gradient slot, so tiles run in parallel without atomics and the sum over
// tiles is deterministic.

#include <torch/extension.h>

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

struct Bins {
  std::vector<int32_t> ids;      // [M] Gaussian index per (tile, Gaussian) pair, front to back within a tile
  std::vector<int64_t> start;    // [n_tiles]
  std::vector<int64_t> count;    // [n_tiles]
};

// The pixel box outside which a Gaussian's alpha is certainly < 1/255: the bounding box of the ellipse
// d^T C d <= 2 ln(255 o), widened by a slack on the exponent (far above float rounding) and one pixel, so the
// exact per-pixel tests decide every borderline case and skipping the rest changes no result. Computed once
// per Gaussian (in double, unclamped) and intersected with each tile by reach_in_tile. [x0, x1) x [y0, y1);
// an unusable conic reaches everywhere (-inf, inf); an opacity below 1/255 (or NaN) reaches nowhere.
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
    if (std::isfinite(ex) && std::isfinite(ey))
      return {std::floor(double(mx) - ex), std::ceil(double(mx) + ex) + 1.0, std::floor(double(my) - ey),
              std::ceil(double(my) + ey) + 1.0};
  }
  return {-inf, inf, -inf, inf};
}

// The pixels [x0, x1) x [y0, y1) of the tile [px0, px1) x [py0, py1) inside the reach box; false when none.
inline bool reach_in_tile(const Reach& R, int px0, int px1, int py0, int py1, int& x0, int& x1, int& y0, int& y1) {
  if (!(std::max<double>(px0, R.x0) < std::min<double>(px1, R.x1) &&
        std::max<double>(py0, R.y0) < std::min<double>(py1, R.y1)))
    return false;
  x0 = static_cast<int>(std::max<double>(px0, R.x0));
  x1 = static_cast<int>(std::min<double>(px1, R.x1));
  y0 = static_cast<int>(std::max<double>(py0, R.y0));
  y1 = static_cast<int>(std::min<double>(py1, R.y1));
  return true;
}

static_assert(sizeof(Reach) == 4 * sizeof(double), "Reach is stored as 4 doubles per Gaussian");

template <typename T>
void reach_boxes(const T* means2d, const T* conics, const T* opac, const int32_t* radii, int64_t n, int threads,
                 Reach* out) {
#pragma omp parallel for schedule(static) num_threads(threads)
  for (int64_t g = 0; g < n; ++g)
    out[g] = radii[g] > 0 ? reach_of<T>(means2d[2 * g], means2d[2 * g + 1], conics[3 * g], conics[3 * g + 1],
                                        conics[3 * g + 2], opac[g])
                          : Reach{1.0, 0.0, 1.0, 0.0};
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

template <typename T>
Bins bin_gaussians(const T* means2d, const T* depths, const int32_t* radii, const Reach* reach, int64_t n, int width,
                   int height) {
  const int tw = (width + TILE - 1) / TILE, th = (height + TILE - 1) / TILE;
  std::vector<int32_t> order;
  order.reserve(n);
  for (int64_t i = 0; i < n; ++i)
    if (radii[i] > 0) order.push_back(static_cast<int32_t>(i));
  std::stable_sort(order.begin(), order.end(), [&](int32_t a, int32_t b) { return depths[a] < depths[b]; });
  Bins bins;
  bins.count.assign(static_cast<size_t>(tw) * th, 0);
  // A (tile, Gaussian) pair is listed only when the reach box meets the tile (the test reach_in_tile makes).
  auto reaches = [&](int32_t g, int tx, int ty) -> bool {
    const int px0 = tx * TILE, py0 = ty * TILE, px1 = std::min(px0 + TILE, width), py1 = std::min(py0 + TILE, height);
    int x0, x1, y0, y1;
    return reach_in_tile(reach[g], px0, px1, py0, py1, x0, x1, y0, y1);
  };
  std::vector<int> rect(order.size() * 4);
  for (size_t k = 0; k < order.size(); ++k) {
    const int32_t g = order[k];
    int* r = &rect[4 * k];
    tile_rect<T>(means2d[2 * g], means2d[2 * g + 1], static_cast<T>(radii[g]), tw, th, r[0], r[1], r[2], r[3]);
    for (int ty = r[2]; ty < r[3]; ++ty)
      for (int tx = r[0]; tx < r[1]; ++tx) bins.count[static_cast<size_t>(ty) * tw + tx] += reaches(g, tx, ty);
  }
  bins.start.assign(bins.count.size(), 0);
  int64_t total = 0;
  for (size_t t = 0; t < bins.count.size(); ++t) {
    bins.start[t] = total;
    total += bins.count[t];
  }
  bins.ids.resize(total);
  std::vector<int64_t> fill(bins.start);
  for (size_t k = 0; k < order.size(); ++k) {
    const int* r = &rect[4 * k];
    for (int ty = r[2]; ty < r[3]; ++ty)
      for (int tx = r[0]; tx < r[1]; ++tx)
        if (reaches(order[k], tx, ty)) bins.ids[fill[static_cast<size_t>(ty) * tw + tx]++] = order[k];
  }
  return bins;
}

// SIMD width of the instruction set this file is compiled for: a tile row (16 pixels) is TILE / W vectors of W
// lanes. A GCC vector wider than the target's registers is lowered to slow generic code (a 16-float row vector
// ran about 15x slower on AVX2 than on AVX-512), so the lane count follows the target.
#if defined(__AVX512F__)
constexpr int VBYTES = 64;
#elif defined(__AVX__)
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

template <typename V>
inline auto hsum(const V& v) {
  auto s = v[0];
  for (int i = 1; i < int(sizeof(V) / sizeof(s)); ++i) s += v[i];
  return s;
}

// exp on K vectors at once. float: Cody-Waite reduction and a degree-7 polynomial (about 2 ulp), branch-free
// SIMD; double (used by the tests): std::exp per lane. The K evaluations are written step by step side by
// side: one Horner chain is a long series of dependent multiplies and adds (no FMA contraction), and a tile
// row's compositing step waits on it; K independent chains in one stretch of code let the CPU overlap them.
// Each vector gets exactly the arithmetic of a single evaluation.
template <int K>
inline void vexp_n(const Simd<float>::V* x, Simd<float>::V* out) {
  using V = Simd<float>::V;
  using M = Simd<float>::M;
  const V lo = splat<V>(-87.0f);  // below this exp underflows; such alphas are far under 1/255 anyway
  V xc[K], kf[K], r[K], p[K];
  for (int j = 0; j < K; ++j) xc[j] = x[j] < lo ? lo : x[j];
  for (int j = 0; j < K; ++j) kf[j] = (xc[j] * 1.44269504088896341f + 12582912.0f) - 12582912.0f;  // round(x/ln2)
  for (int j = 0; j < K; ++j) r[j] = (xc[j] - kf[j] * 0.693145751953125f) - kf[j] * 1.428606765330187e-06f;
  for (int j = 0; j < K; ++j) p[j] = splat<V>(1.0f / 5040.0f);
  for (int j = 0; j < K; ++j) p[j] = p[j] * r[j] + 1.0f / 720.0f;
  for (int j = 0; j < K; ++j) p[j] = p[j] * r[j] + 1.0f / 120.0f;
  for (int j = 0; j < K; ++j) p[j] = p[j] * r[j] + 1.0f / 24.0f;
  for (int j = 0; j < K; ++j) p[j] = p[j] * r[j] + 1.0f / 6.0f;
  for (int j = 0; j < K; ++j) p[j] = p[j] * r[j] + 0.5f;
  for (int j = 0; j < K; ++j) p[j] = p[j] * r[j] + 1.0f;
  for (int j = 0; j < K; ++j) p[j] = p[j] * r[j] + 1.0f;
  for (int j = 0; j < K; ++j) {
    const M bits = (__builtin_convertvector(kf[j], M) + 127) << 23;
    out[j] = p[j] * reinterpret_cast<const V&>(bits);
  }
}
template <int K>
inline void vexp_n(const Simd<double>::V* x, Simd<double>::V* out) {
  for (int j = 0; j < K; ++j)
    for (int i = 0; i < Simd<double>::W; ++i) out[j][i] = std::exp(x[j][i]);
}

// The vectors [c0, c1) of a tile row that hold pixels x0..x1-1 (tile starting at px0).
template <int W>
inline void lane_span(int x0, int x1, int px0, int& c0, int& c1) {
  c0 = (x0 - px0) / W;
  c1 = (x1 - px0 + W - 1) / W;
}

template <typename T>
void forward_impl(const T* means2d, const T* conics, const T* opac, const T* colors, const T* depths, const T* bg,
                  const Reach* reach, const Bins& bins, int width, int height, int threads, T* out_rgb, T* out_alpha,
                  T* out_depth, T* out_T, int32_t* out_last) {
  using V = typename Simd<T>::V;
  using M = typename Simd<T>::M;
  constexpr int W = Simd<T>::W, N = Simd<T>::N;
  const int tw = (width + TILE - 1) / TILE, th = (height + TILE - 1) / TILE;
  const int n_tiles = tw * th;
  const V amax = splat<V>(Consts<T>::alpha_max), zero = splat<V>(0), one = splat<V>(1);
  const T amin = Consts<T>::alpha_min, tmin = Consts<T>::t_min;
#pragma omp parallel for schedule(dynamic, 1) num_threads(threads)
  for (int t = 0; t < n_tiles; ++t) {
    const int px0 = (t % tw) * TILE, py0 = (t / tw) * TILE;
    const int px1 = std::min(px0 + TILE, width), py1 = std::min(py0 + TILE, height);
    const int n_pix = (px1 - px0) * (py1 - py0);
    // Per pixel: transmittance, accumulated r, g, b, depth, index+1 of the last composited Gaussian (as T:
    // exact below 2^24 per tile, checked by the caller), and a finished flag; [row][vector] with W lanes.
    V Tr[TILE][N], ar[TILE][N], ag[TILE][N], ab[TILE][N], az[TILE][N], last[TILE][N], done[TILE][N];
    V xs[N];
    for (int c = 0; c < N; ++c)
      for (int i = 0; i < W; ++i) xs[c][i] = T(px0 + c * W + i);
    for (int r = 0; r < TILE; ++r)
      for (int c = 0; c < N; ++c) {
        Tr[r][c] = one;
        ar[r][c] = ag[r][c] = ab[r][c] = az[r][c] = last[r][c] = zero;
        // Pixels of a partial tile that lie outside the image are born finished.
        for (int i = 0; i < W; ++i) done[r][c][i] = (px0 + c * W + i < px1 && py0 + r < py1) ? T(0) : T(1);
      }
    M stopped = splat<M>(0);  // lanes hold -(number of pixels of that lane that finished)
    const int64_t s = bins.start[t], cnt = bins.count[t];
    for (int64_t k = 0; k < cnt; ++k) {
      const int32_t g = bins.ids[s + k];
      const T mx = means2d[2 * g], my = means2d[2 * g + 1];
      const T ca = conics[3 * g], cb = conics[3 * g + 1], cc = conics[3 * g + 2];
      const T o = opac[g];
      int x0, x1, y0, y1, c0, c1;
      if (!reach_in_tile(reach[g], px0, px1, py0, py1, x0, x1, y0, y1)) continue;
      lane_span<W>(x0, x1, px0, c0, c1);
      const T cr = colors[3 * g], cg = colors[3 * g + 1], cbl = colors[3 * g + 2], z = depths[g];
      const V kk = splat<V>(k + 1);
      V dx[N], cdx[N];
      for (int c = c0; c < c1; ++c) {
        dx[c] = xs[c] - mx;
        cdx[c] = ca * dx[c] * dx[c];
      }
      // Rows y .. y+K-1 (K = 4 while four rows are left, then 2, then 1): first the exps of all their row
      // vectors, K rows side by side (vexp_n), then the compositing row by row, vector by vector as one row at
      // a time would: every pixel gets the same arithmetic in the same order. (One row at a time waited on
      // each row's exp chain: about 90 cycles per 16-pixel row vector on Zen 4; four side by side cut the
      // kernel's CPU time by about a fifth, bit-identical results.)
      auto rows = [&](auto k_rows, int y) {
        constexpr int K = decltype(k_rows)::value;
        V power[K][N], e[K][N];
        for (int c = c0; c < c1; ++c) {
          V pw[K], ex[K];
          for (int j = 0; j < K; ++j) {
            const T dy = T(y + j) - my;
            const T cdy = cc * dy * dy;
            pw[j] = T(-0.5) * (cdx[c] + cdy) - cb * dx[c] * dy;
          }
          vexp_n<K>(pw, ex);
          for (int j = 0; j < K; ++j) power[j][c] = pw[j], e[j][c] = ex[j];
        }
        for (int j = 0; j < K; ++j) {
          const int r = y + j - py0;
          for (int c = c0; c < c1; ++c) {
            V alpha = o * e[j][c];
            alpha = alpha < amax ? alpha : amax;
            V& tr = Tr[r][c];
            const M ok = (done[r][c] == T(0)) & (power[j][c] <= T(0)) & (alpha >= amin);
            const V next = tr * (T(1) - alpha);
            const M stop = ok & (next < tmin);
            const M use = ok & ~stop;
            const V w = use ? alpha * tr : zero;
            ar[r][c] += w * cr;
            ag[r][c] += w * cg;
            ab[r][c] += w * cbl;
            az[r][c] += w * z;
            tr = use ? next : tr;
            last[r][c] = use ? kk : last[r][c];
            done[r][c] = stop ? one : done[r][c];
            stopped += stop;
          }
        }
      };
      int y = y0;
      for (; y + 3 < y1; y += 4) rows(std::integral_constant<int, 4>(), y);
      if (y + 1 < y1) rows(std::integral_constant<int, 2>(), y), y += 2;
      if (y < y1) rows(std::integral_constant<int, 1>(), y);
      if (-hsum(stopped) >= n_pix) break;
    }
    for (int y = py0; y < py1; ++y)
      for (int x = px0; x < px1; ++x) {
        const int r = y - py0, c = (x - px0) / W, i = (x - px0) % W;
        const int64_t q = static_cast<int64_t>(y) * width + x;
        const T tr = Tr[r][c][i];
        out_rgb[3 * q] = ar[r][c][i] + tr * bg[0];
        out_rgb[3 * q + 1] = ag[r][c][i] + tr * bg[1];
        out_rgb[3 * q + 2] = ab[r][c][i] + tr * bg[2];
        out_alpha[q] = T(1) - tr;
        out_depth[q] = az[r][c][i];
        out_T[q] = tr;
        out_last[q] = static_cast<int32_t>(last[r][c][i]);
      }
  }
}

template <typename T>
void backward_impl(const T* means2d, const T* conics, const T* opac, const T* colors, const T* depths, const T* bg,
                   const Reach* reach, const int32_t* ids, const int64_t* tstart, const int64_t* tcount, const T* final_T,
                   const int32_t* last_in, const T* g_rgb, const T* g_alpha, const T* g_depth, int width, int height,
                   int threads, T* pair_grad) {
  using V = typename Simd<T>::V;
  using M = typename Simd<T>::M;
  constexpr int W = Simd<T>::W, N = Simd<T>::N;
  const int tw = (width + TILE - 1) / TILE, th = (height + TILE - 1) / TILE;
  const int n_tiles = tw * th;
  const V amax = splat<V>(Consts<T>::alpha_max), zero = splat<V>(0);
  const T amin = Consts<T>::alpha_min;
#pragma omp parallel for schedule(dynamic, 1) num_threads(threads)
  for (int t = 0; t < n_tiles; ++t) {
    const int64_t s = tstart[t];
    if (tcount[t] == 0) continue;
    const int px0 = (t % tw) * TILE, py0 = (t / tw) * TILE;
    const int px1 = std::min(px0 + TILE, width), py1 = std::min(py0 + TILE, height);
    // Per pixel ([row][vector], W lanes): Tr = transmittance behind the Gaussians still to visit; B* = normalised
    // colour behind them (r, g, b, depth, alpha channel); G* = dL/d(output); last = composited count (0 outside).
    V Tr[TILE][N], Br[TILE][N], Bg[TILE][N], Bb[TILE][N], Bz[TILE][N], Ba[TILE][N];
    V Gr[TILE][N], Gg[TILE][N], Gb[TILE][N], Gz[TILE][N], Ga[TILE][N], last[TILE][N];
    V xs[N];
    for (int c = 0; c < N; ++c)
      for (int i = 0; i < W; ++i) xs[c][i] = T(px0 + c * W + i);
    for (int r = 0; r < TILE; ++r)
      for (int c = 0; c < N; ++c) {
        Tr[r][c] = splat<V>(1);
        Br[r][c] = splat<V>(bg[0]), Bg[r][c] = splat<V>(bg[1]), Bb[r][c] = splat<V>(bg[2]);
        Bz[r][c] = Ba[r][c] = Gr[r][c] = Gg[r][c] = Gb[r][c] = Gz[r][c] = Ga[r][c] = last[r][c] = zero;
      }
    int32_t max_last = 0;
    for (int y = py0; y < py1; ++y)
      for (int x = px0; x < px1; ++x) {
        const int r = y - py0, c = (x - px0) / W, i = (x - px0) % W;
        const int64_t q = static_cast<int64_t>(y) * width + x;
        Tr[r][c][i] = final_T[q];
        last[r][c][i] = T(last_in[q]);
        max_last = std::max(max_last, last_in[q]);
        Gr[r][c][i] = g_rgb[3 * q], Gg[r][c][i] = g_rgb[3 * q + 1], Gb[r][c][i] = g_rgb[3 * q + 2];
        Gz[r][c][i] = g_depth[q], Ga[r][c][i] = g_alpha[q];
      }
    for (int64_t k = max_last - 1; k >= 0; --k) {
      const int32_t g = ids[s + k];
      const T mx = means2d[2 * g], my = means2d[2 * g + 1];
      const T ca = conics[3 * g], cb = conics[3 * g + 1], cc = conics[3 * g + 2];
      const T o = opac[g];
      int x0, x1, y0, y1, c0, c1;
      if (!reach_in_tile(reach[g], px0, px1, py0, py1, x0, x1, y0, y1)) continue;
      lane_span<W>(x0, x1, px0, c0, c1);
      const T cr = colors[3 * g], cg = colors[3 * g + 1], cbl = colors[3 * g + 2], z = depths[g];
      const V kk = splat<V>(k);
      V dx[N], cdx[N];
      for (int c = c0; c < c1; ++c) {
        dx[c] = xs[c] - mx;
        cdx[c] = ca * dx[c] * dx[c];
      }
      V d_mx = zero, d_my = zero, d_a = zero, d_b = zero, d_c = zero, d_o = zero;
      V d_r = zero, d_g = zero, d_bl = zero, d_z = zero;
      // As in the forward: the exps of rows y .. y+K-1 side by side, then the rest row by row, vector by vector
      // in the order of one row at a time (the gradient sums add their terms in the same order).
      auto rows = [&](auto k_rows, int y) {
        constexpr int K = decltype(k_rows)::value;
        V power[K][N], ga[K][N];
        for (int c = c0; c < c1; ++c) {
          V pw[K], ex[K];
          for (int j = 0; j < K; ++j) {
            const T dy = T(y + j) - my;
            const T cdy = cc * dy * dy;
            pw[j] = T(-0.5) * (cdx[c] + cdy) - cb * dx[c] * dy;
          }
          vexp_n<K>(pw, ex);
          for (int j = 0; j < K; ++j) power[j][c] = pw[j], ga[j][c] = ex[j];
        }
        for (int j = 0; j < K; ++j) {
          const int r = y + j - py0;
          const T dy = T(y + j) - my;
          for (int c = c0; c < c1; ++c) {
            const V gauss = ga[j][c];
            const V raw = o * gauss;
            const V alpha = raw < amax ? raw : amax;
            const M active = (kk < last[r][c]) & (power[j][c] <= T(0)) & (alpha >= amin);
            V& tr = Tr[r][c];
            const V t_k = tr / (T(1) - alpha);  // transmittance in front of this Gaussian
            const V w = active ? alpha * t_k : zero;
            d_r += w * Gr[r][c];
            d_g += w * Gg[r][c];
            d_bl += w * Gb[r][c];
            d_z += w * Gz[r][c];
            V d_alpha = Gr[r][c] * (cr - Br[r][c]) + Gg[r][c] * (cg - Bg[r][c]) + Gb[r][c] * (cbl - Bb[r][c]) +
                        Gz[r][c] * (z - Bz[r][c]) + Ga[r][c] * (T(1) - Ba[r][c]);
            d_alpha = (active & (raw <= amax)) ? d_alpha * t_k : zero;  // clamped alpha: no gradient
            const V keep = T(1) - alpha;
            Br[r][c] = active ? alpha * cr + keep * Br[r][c] : Br[r][c];
            Bg[r][c] = active ? alpha * cg + keep * Bg[r][c] : Bg[r][c];
            Bb[r][c] = active ? alpha * cbl + keep * Bb[r][c] : Bb[r][c];
            Bz[r][c] = active ? alpha * z + keep * Bz[r][c] : Bz[r][c];
            Ba[r][c] = active ? alpha + keep * Ba[r][c] : Ba[r][c];
            tr = active ? t_k : tr;
            d_o += gauss * d_alpha;
            const V d_pow = raw * d_alpha;
            d_a += T(-0.5) * dx[c] * dx[c] * d_pow;
            d_c += T(-0.5) * dy * dy * d_pow;
            d_b += -dx[c] * dy * d_pow;
            d_mx += (ca * dx[c] + cb * dy) * d_pow;
            d_my += (cb * dx[c] + cc * dy) * d_pow;
          }
        }
      };
      int y = y0;
      for (; y + 3 < y1; y += 4) rows(std::integral_constant<int, 4>(), y);
      if (y + 1 < y1) rows(std::integral_constant<int, 2>(), y), y += 2;
      if (y < y1) rows(std::integral_constant<int, 1>(), y);
      T* slot = pair_grad + (s + k) * NGRAD;
      slot[0] = hsum(d_mx), slot[1] = hsum(d_my), slot[2] = hsum(d_a), slot[3] = hsum(d_b), slot[4] = hsum(d_c);
      slot[5] = hsum(d_o), slot[6] = hsum(d_r), slot[7] = hsum(d_g), slot[8] = hsum(d_bl), slot[9] = hsum(d_z);
    }
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

Camera make_camera(const torch::Tensor& K, const torch::Tensor& w2c, int64_t width, int64_t height, double near,
                   double eps2d) {
  auto k = K.to(torch::kDouble).contiguous();
  auto v = w2c.to(torch::kDouble).contiguous();
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

// Everything the forward computes for one Gaussian, kept for its backward.
struct ProjState {
  double m[3], qn, qh[4], s[3], Rq[9], M[9], p[3], rz, X, Y, xin, yin, W[9], A0[3], A1[3], a, b, c, det;
  double C[3];  // A0 x A1, from the scaled minors (accurate where the rows are nearly parallel)
};

// Returns false when the Gaussian is culled before its covariance is known to be usable.
inline bool project_one(const Camera& cam, const double* m, const double* q, const double* ls, ProjState& S) {
  for (int i = 0; i < 3; ++i)
    if (!std::isfinite(m[i]) || !std::isfinite(ls[i])) return false;
  for (int i = 0; i < 4; ++i)
    if (!std::isfinite(q[i])) return false;
  S.qn = std::sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3]);
  if (!(S.qn > 1e-8)) return false;
  for (int i = 0; i < 3; ++i) S.m[i] = m[i];
  for (int r = 0; r < 3; ++r)
    S.p[r] = cam.R[3 * r] * m[0] + cam.R[3 * r + 1] * m[1] + cam.R[3 * r + 2] * m[2] + cam.t[r];
  if (!(std::isfinite(S.p[0]) && std::isfinite(S.p[1]) && std::isfinite(S.p[2]) && S.p[2] > cam.near)) return false;
  for (int i = 0; i < 4; ++i) S.qh[i] = q[i] / S.qn;
  const double w = S.qh[0], x = S.qh[1], y = S.qh[2], z = S.qh[3];
  const double Rq[9] = {1 - 2 * (y * y + z * z), 2 * (x * y - w * z),     2 * (x * z + w * y),
                        2 * (x * y + w * z),     1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
                        2 * (x * z - w * y),     2 * (y * z + w * x),     1 - 2 * (x * x + y * y)};
  for (int i = 0; i < 3; ++i) S.s[i] = std::exp(ls[i]);
  for (int j = 0; j < 3; ++j)
    for (int k = 0; k < 3; ++k) {
      S.Rq[3 * j + k] = Rq[3 * j + k];
      S.M[3 * j + k] = Rq[3 * j + k] * S.s[k];
    }
  // Bq = R Rq, so W = R M = Bq diag(s); B = J Bq and A = J W = B diag(s). B also gives the determinant below.
  double Bq[9];
  for (int r = 0; r < 3; ++r)
    for (int k = 0; k < 3; ++k) {
      Bq[3 * r + k] = cam.R[3 * r] * Rq[k] + cam.R[3 * r + 1] * Rq[3 + k] + cam.R[3 * r + 2] * Rq[6 + k];
      S.W[3 * r + k] = Bq[3 * r + k] * S.s[k];
    }
  S.rz = 1.0 / S.p[2];
  const double xr = S.p[0] * S.rz, yr = S.p[1] * S.rz;
  S.X = std::min(std::max(xr, -cam.lxn), cam.lxp);
  S.Y = std::min(std::max(yr, -cam.lyn), cam.lyp);
  S.xin = (xr > -cam.lxn && xr < cam.lxp) ? 1.0 : 0.0;  // direction not clamped: J follows x
  S.yin = (yr > -cam.lyn && yr < cam.lyp) ? 1.0 : 0.0;
  const double j00 = cam.fx * S.rz, j02 = -cam.fx * S.X * S.rz, j11 = cam.fy * S.rz, j12 = -cam.fy * S.Y * S.rz;
  double B0[3], B1[3];
  for (int k = 0; k < 3; ++k) {
    B0[k] = j00 * Bq[k] + j02 * Bq[6 + k];
    B1[k] = j11 * Bq[3 + k] + j12 * Bq[6 + k];
    S.A0[k] = B0[k] * S.s[k];
    S.A1[k] = B1[k] * S.s[k];
  }
  const double sq0 = S.A0[0] * S.A0[0] + S.A0[1] * S.A0[1] + S.A0[2] * S.A0[2];
  const double sq1 = S.A1[0] * S.A1[0] + S.A1[1] * S.A1[1] + S.A1[2] * S.A1[2];
  S.a = sq0 + cam.eps2d;
  S.b = S.A0[0] * S.A1[0] + S.A0[1] * S.A1[1] + S.A0[2] * S.A1[2];
  S.c = sq1 + cam.eps2d;
  // det = a c - b^2, written without its cancellation (which leaves only rounding noise, of either sign, for
  // large thin footprints): by Cauchy-Binet det(A A^T) is the sum over column pairs of
  // (s_i s_j minor_ij(B))^2, and the eps2d terms are positive. Same as projection.py.
  const double t01 = S.s[0] * S.s[1] * (B0[0] * B1[1] - B0[1] * B1[0]);
  const double t02 = S.s[0] * S.s[2] * (B0[0] * B1[2] - B0[2] * B1[0]);
  const double t12 = S.s[1] * S.s[2] * (B0[1] * B1[2] - B0[2] * B1[1]);
  S.det = t01 * t01 + t02 * t02 + t12 * t12 + cam.eps2d * (sq0 + sq1) + cam.eps2d * cam.eps2d;
  S.C[0] = t12, S.C[1] = -t02, S.C[2] = t01;
  return std::isfinite(S.a) && std::isfinite(S.b) && std::isfinite(S.c) && std::isfinite(S.det) && S.det > 0 &&
         std::isfinite(S.c / S.det) && std::isfinite(S.a / S.det);
}

template <typename T>
void project_forward_impl(const Camera& cam, const T* means, const T* quats, const T* lsc, const bool* keep, int64_t n,
                          int threads, T* means2d, T* conics, T* depths, int32_t* radii) {
  const int tw = (cam.width + TILE - 1) / TILE, th = (cam.height + TILE - 1) / TILE;
#pragma omp parallel for schedule(static) num_threads(threads)
  for (int64_t i = 0; i < n; ++i) {
    means2d[2 * i] = means2d[2 * i + 1] = T(0);
    conics[3 * i] = conics[3 * i + 1] = conics[3 * i + 2] = T(0);
    depths[i] = T(0);
    radii[i] = 0;
    if (!keep[i]) continue;
    const double m[3] = {double(means[3 * i]), double(means[3 * i + 1]), double(means[3 * i + 2])};
    const double q[4] = {double(quats[4 * i]), double(quats[4 * i + 1]), double(quats[4 * i + 2]),
                         double(quats[4 * i + 3])};
    const double ls[3] = {double(lsc[3 * i]), double(lsc[3 * i + 1]), double(lsc[3 * i + 2])};
    ProjState S;
    if (!project_one(cam, m, q, ls, S)) continue;
    {
      // Cull what the storage type cannot hold, as the PyTorch projection does in that dtype: a covariance or
      // determinant that overflows, or a conic that is not finite and positive on its diagonal.
      const T ta = T(S.a), tc = T(S.c), tdet = T(S.det);
      const T c0 = T(S.c / S.det), c1 = T(-S.b / S.det), c2 = T(S.a / S.det);
      if (!(std::isfinite(double(tdet)) && tdet > T(0) && std::isfinite(double(ta)) && std::isfinite(double(tc))))
        continue;
      if (!(std::isfinite(double(c0)) && std::isfinite(double(c1)) && std::isfinite(double(c2)) && c0 > T(0) &&
            c2 > T(0)))
        continue;
    }
    const double mid = 0.5 * (S.a + S.c);
    double r = std::ceil(3.0 * std::sqrt(mid + std::sqrt(std::max(mid * mid - S.det, 0.1))));
    r = std::min(r, double(1 << 24));
    if (!(r > 0)) continue;
    const T u = T(cam.fx * S.p[0] * S.rz + cam.cx), v = T(cam.fy * S.p[1] * S.rz + cam.cy);
    if (!std::isfinite(double(u)) || !std::isfinite(double(v))) continue;
    int x0, x1, y0, y1;
    tile_rect<T>(u, v, T(r), tw, th, x0, x1, y0, y1);
    if (!(x1 > x0 && y1 > y0)) continue;
    means2d[2 * i] = u, means2d[2 * i + 1] = v;
    conics[3 * i] = T(S.c / S.det), conics[3 * i + 1] = T(-S.b / S.det), conics[3 * i + 2] = T(S.a / S.det);
    depths[i] = T(S.p[2]);
    radii[i] = static_cast<int32_t>(r);
  }
}

template <typename T>
void project_backward_impl(const Camera& cam, const T* means, const T* quats, const T* lsc, const int32_t* radii,
                           int64_t n, const T* g_m2d, const T* g_con, const T* g_z, int threads, T* d_means,
                           T* d_quats, T* d_ls, double* d_Rt /* [n][12], summed by the caller in order */) {
#pragma omp parallel num_threads(threads)
  {
#pragma omp for schedule(static)
    for (int64_t i = 0; i < n; ++i) {
      double* acc = d_Rt + 12 * i;
      for (int k = 0; k < 3; ++k) d_means[3 * i + k] = d_ls[3 * i + k] = T(0);
      for (int k = 0; k < 4; ++k) d_quats[4 * i + k] = T(0);
      if (radii[i] <= 0) continue;  // culled: exactly zero gradient
      const double m[3] = {double(means[3 * i]), double(means[3 * i + 1]), double(means[3 * i + 2])};
      const double q[4] = {double(quats[4 * i]), double(quats[4 * i + 1]), double(quats[4 * i + 2]),
                           double(quats[4 * i + 3])};
      const double ls[3] = {double(lsc[3 * i]), double(lsc[3 * i + 1]), double(lsc[3 * i + 2])};
      ProjState S;
      if (!project_one(cam, m, q, ls, S)) continue;
      const double a = S.a, b = S.b, c = S.c, det = S.det, d2 = det * det;
      const double g0 = double(g_con[3 * i]), g1 = double(g_con[3 * i + 1]), g2 = double(g_con[3 * i + 2]);
      // conic = (c, -b, a) / det. The numerators go through a, b, c; det through its own gradient,
      // d det / dA0 = 2 (A1 x C + eps A0), d det / dA1 = 2 (C x A0 + eps A1) with C = A0 x A1: going through
      // d(a c - b^2) instead would cancel huge terms for long thin footprints (as the forward would).
      const double ga = g2 / det, gb = -g1 / det, gc = g0 / det;
      const double gdet = -(g0 * c - g1 * b + g2 * a) / d2;
      const double* A0 = S.A0;
      const double* A1 = S.A1;
      const double* C = S.C;
      const double A1xC[3] = {A1[1] * C[2] - A1[2] * C[1], A1[2] * C[0] - A1[0] * C[2], A1[0] * C[1] - A1[1] * C[0]};
      const double CxA0[3] = {C[1] * A0[2] - C[2] * A0[1], C[2] * A0[0] - C[0] * A0[2], C[0] * A0[1] - C[1] * A0[0]};
      double dA0[3], dA1[3];
      for (int k = 0; k < 3; ++k) {
        dA0[k] = 2 * ga * A0[k] + gb * A1[k] + 2 * gdet * (A1xC[k] + cam.eps2d * A0[k]);
        dA1[k] = gb * A0[k] + 2 * gc * A1[k] + 2 * gdet * (CxA0[k] + cam.eps2d * A1[k]);
      }
      const double rz = S.rz, fx = cam.fx, fy = cam.fy;
      const double j00 = fx * rz, j02 = -fx * S.X * rz, j11 = fy * rz, j12 = -fy * S.Y * rz;
      double dW[9];
      double dj00 = 0, dj02 = 0, dj11 = 0, dj12 = 0;
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
      double dR[9], dM[9];
      for (int r = 0; r < 3; ++r)
        for (int j = 0; j < 3; ++j)
          dR[3 * r + j] = dW[3 * r] * S.M[3 * j] + dW[3 * r + 1] * S.M[3 * j + 1] + dW[3 * r + 2] * S.M[3 * j + 2];
      for (int j = 0; j < 3; ++j)
        for (int k = 0; k < 3; ++k)
          dM[3 * j + k] = cam.R[j] * dW[k] + cam.R[3 + j] * dW[3 + k] + cam.R[6 + j] * dW[6 + k];
      // M = Rq diag(s), s = exp(log_scales).
      double dRq[9];
      for (int k = 0; k < 3; ++k) {
        double ds = 0;
        for (int j = 0; j < 3; ++j) {
          dRq[3 * j + k] = dM[3 * j + k] * S.s[k];
          ds += dM[3 * j + k] * S.Rq[3 * j + k];
        }
        d_ls[3 * i + k] = T(ds * S.s[k]);
      }
      const double w = S.qh[0], x = S.qh[1], y = S.qh[2], z = S.qh[3];
      const double* G = dRq;
      const double dqh[4] = {
          2 * (-z * G[1] + y * G[2] + z * G[3] - x * G[5] - y * G[6] + x * G[7]),
          2 * (y * G[1] + z * G[2] + y * G[3] - 2 * x * G[4] - w * G[5] + z * G[6] + w * G[7] - 2 * x * G[8]),
          2 * (-2 * y * G[0] + x * G[1] + w * G[2] + x * G[3] + z * G[5] - w * G[6] + z * G[7] - 2 * y * G[8]),
          2 * (-2 * z * G[0] - w * G[1] + x * G[2] + w * G[3] - 2 * z * G[4] + y * G[5] + x * G[6] + y * G[7])};
      const double dot = dqh[0] * S.qh[0] + dqh[1] * S.qh[1] + dqh[2] * S.qh[2] + dqh[3] * S.qh[3];
      for (int k = 0; k < 4; ++k) d_quats[4 * i + k] = T((dqh[k] - S.qh[k] * dot) / S.qn);
      // Camera point p: from the 2D mean, the depth and the Jacobian entries.
      const double gu = double(g_m2d[2 * i]), gv = double(g_m2d[2 * i + 1]);
      const double px = S.p[0], py = S.p[1];
      double dp[3];
      dp[0] = gu * fx * rz - dj02 * fx * rz * S.xin * rz;
      dp[1] = gv * fy * rz - dj12 * fy * rz * S.yin * rz;
      dp[2] = double(g_z[i]) - gu * fx * px * rz * rz - gv * fy * py * rz * rz - dj00 * fx * rz * rz -
              dj11 * fy * rz * rz - dj02 * fx * (S.xin * (-px * rz * rz) * rz - S.X * rz * rz) -
              dj12 * fy * (S.yin * (-py * rz * rz) * rz - S.Y * rz * rz);
      // p = R m + t.
      for (int j = 0; j < 3; ++j)
        d_means[3 * i + j] = T(cam.R[j] * dp[0] + cam.R[3 + j] * dp[1] + cam.R[6 + j] * dp[2]);
      for (int r = 0; r < 3; ++r) {
        for (int j = 0; j < 3; ++j) acc[3 * r + j] += dR[3 * r + j] + dp[r] * S.m[j];
        acc[9 + r] += dp[r];
      }
    }
  }
}

void check(const torch::Tensor& t, const char* name, int64_t n, int64_t cols) {
  TORCH_CHECK(t.device().is_cpu(), name, " must be a CPU tensor");
  TORCH_CHECK(t.is_contiguous(), name, " must be contiguous");
  TORCH_CHECK(t.size(0) == n, name, " has the wrong length");
  if (cols > 0) TORCH_CHECK(t.dim() == 2 && t.size(1) == cols, name, " has the wrong shape");
}

}  // namespace

// Returns rgb [H,W,3], alpha [H,W], depth [H,W], final_T [H,W], last [H,W] int32, ids [M] int32,
// tile_start [n_tiles] int64, tile_count [n_tiles] int64, reach [N,4] double (each Gaussian's reach box).
std::vector<torch::Tensor> rasterize_forward(torch::Tensor means2d, torch::Tensor conics, torch::Tensor opac,
                                             torch::Tensor colors, torch::Tensor depths, torch::Tensor radii,
                                             torch::Tensor bg, int64_t width, int64_t height, int64_t threads) {
  const int64_t n = means2d.size(0);
  check(means2d, "means2d", n, 2);
  check(conics, "conics", n, 3);
  check(opac, "opacities", n, 0);
  check(colors, "colors", n, 3);
  check(depths, "depths", n, 0);
  check(radii, "radii", n, 0);
  TORCH_CHECK(radii.scalar_type() == torch::kInt32, "radii must be int32");
  auto opts = means2d.options();
  auto rgb = torch::empty({height, width, 3}, opts);
  auto alpha = torch::empty({height, width}, opts);
  auto depth = torch::empty({height, width}, opts);
  auto final_T = torch::empty({height, width}, opts);
  auto last = torch::empty({height, width}, opts.dtype(torch::kInt32));
  auto reach = torch::empty({n, 4}, opts.dtype(torch::kDouble));
  Reach* boxes = reinterpret_cast<Reach*>(reach.data_ptr<double>());
  torch::Tensor ids, tstart, tcount;
  AT_DISPATCH_FLOATING_TYPES(means2d.scalar_type(), "rasterize_forward", [&] {
    reach_boxes<scalar_t>(means2d.data_ptr<scalar_t>(), conics.data_ptr<scalar_t>(), opac.data_ptr<scalar_t>(),
                          radii.data_ptr<int32_t>(), n, int(threads), boxes);
    Bins bins = bin_gaussians<scalar_t>(means2d.data_ptr<scalar_t>(), depths.data_ptr<scalar_t>(),
                                        radii.data_ptr<int32_t>(), boxes, n, int(width), int(height));
    for (int64_t c : bins.count)
      TORCH_CHECK(c < (int64_t(1) << 24), "more than 2^24 Gaussians in one tile; use the reference backend");
    forward_impl<scalar_t>(means2d.data_ptr<scalar_t>(), conics.data_ptr<scalar_t>(), opac.data_ptr<scalar_t>(),
                           colors.data_ptr<scalar_t>(), depths.data_ptr<scalar_t>(), bg.data_ptr<scalar_t>(), boxes, bins,
                           int(width), int(height), int(threads), rgb.data_ptr<scalar_t>(),
                           alpha.data_ptr<scalar_t>(), depth.data_ptr<scalar_t>(), final_T.data_ptr<scalar_t>(),
                           last.data_ptr<int32_t>());
    const int64_t m = static_cast<int64_t>(bins.ids.size()), nt = static_cast<int64_t>(bins.start.size());
    ids = torch::empty({m}, opts.dtype(torch::kInt32));
    tstart = torch::empty({nt}, opts.dtype(torch::kInt64));
    tcount = torch::empty({nt}, opts.dtype(torch::kInt64));
    std::copy(bins.ids.begin(), bins.ids.end(), ids.data_ptr<int32_t>());
    std::copy(bins.start.begin(), bins.start.end(), tstart.data_ptr<int64_t>());
    std::copy(bins.count.begin(), bins.count.end(), tcount.data_ptr<int64_t>());
  });
  return {rgb, alpha, depth, final_T, last, ids, tstart, tcount, reach};
}

// Returns gradients: means2d [N,2], conics [N,3], opacities [N], colors [N,3], depths [N].
std::vector<torch::Tensor> rasterize_backward(torch::Tensor means2d, torch::Tensor conics, torch::Tensor opac,
                                              torch::Tensor colors, torch::Tensor depths, torch::Tensor bg,
                                              torch::Tensor reach, torch::Tensor ids, torch::Tensor tstart, torch::Tensor tcount,
                                              torch::Tensor final_T, torch::Tensor last, torch::Tensor g_rgb,
                                              torch::Tensor g_alpha, torch::Tensor g_depth, int64_t width,
                                              int64_t height, int64_t threads) {
  const int64_t n = means2d.size(0), m = ids.size(0);
  TORCH_CHECK(g_rgb.is_contiguous() && g_alpha.is_contiguous() && g_depth.is_contiguous(),
              "output gradients must be contiguous");
  TORCH_CHECK(reach.scalar_type() == torch::kDouble && reach.is_contiguous() && reach.dim() == 2 &&
                  reach.size(0) == n && reach.size(1) == 4,
              "reach must be the [N, 4] double tensor the forward returned");
  const Reach* boxes = reinterpret_cast<const Reach*>(reach.data_ptr<double>());
  auto opts = means2d.options();
  auto pair_grad = torch::zeros({m, NGRAD}, opts);
  auto grad = torch::zeros({n, NGRAD}, opts);
  AT_DISPATCH_FLOATING_TYPES(means2d.scalar_type(), "rasterize_backward", [&] {
    backward_impl<scalar_t>(means2d.data_ptr<scalar_t>(), conics.data_ptr<scalar_t>(), opac.data_ptr<scalar_t>(),
                            colors.data_ptr<scalar_t>(), depths.data_ptr<scalar_t>(), bg.data_ptr<scalar_t>(), boxes,
                            ids.data_ptr<int32_t>(), tstart.data_ptr<int64_t>(), tcount.data_ptr<int64_t>(),
                            final_T.data_ptr<scalar_t>(), last.data_ptr<int32_t>(), g_rgb.data_ptr<scalar_t>(),
                            g_alpha.data_ptr<scalar_t>(), g_depth.data_ptr<scalar_t>(), int(width), int(height),
                            int(threads), pair_grad.data_ptr<scalar_t>());
    // Sum the per-(tile, Gaussian) slots into per-Gaussian gradients, in tile order (deterministic).
    const scalar_t* pg = pair_grad.data_ptr<scalar_t>();
    scalar_t* gr = grad.data_ptr<scalar_t>();
    const int32_t* id = ids.data_ptr<int32_t>();
    for (int64_t j = 0; j < m; ++j)
      for (int c = 0; c < NGRAD; ++c) gr[int64_t(id[j]) * NGRAD + c] += pg[j * NGRAD + c];
  });
  using torch::indexing::Slice;
  return {grad.index({Slice(), Slice(0, 2)}), grad.index({Slice(), Slice(2, 5)}), grad.index({Slice(), 5}),
          grad.index({Slice(), Slice(6, 9)}), grad.index({Slice(), 9})};
}

// Returns means2d [N,2], conics [N,3], depths [N], radii [N] int32 (zeros where culled).
std::vector<torch::Tensor> project_forward(torch::Tensor means, torch::Tensor quats, torch::Tensor log_scales,
                                           torch::Tensor K, torch::Tensor w2c, torch::Tensor keep, int64_t width,
                                           int64_t height, double near, double eps2d, int64_t threads) {
  const int64_t n = means.size(0);
  check(means, "means", n, 3);
  check(quats, "quats", n, 4);
  check(log_scales, "log_scales", n, 3);
  check(keep, "keep", n, 0);
  TORCH_CHECK(keep.scalar_type() == torch::kBool, "keep must be bool");
  const Camera cam = make_camera(K, w2c, width, height, near, eps2d);
  auto opts = means.options();
  auto means2d = torch::empty({n, 2}, opts), conics = torch::empty({n, 3}, opts), depths = torch::empty({n}, opts);
  auto radii = torch::empty({n}, opts.dtype(torch::kInt32));
  AT_DISPATCH_FLOATING_TYPES(means.scalar_type(), "project_forward", [&] {
    project_forward_impl<scalar_t>(cam, means.data_ptr<scalar_t>(), quats.data_ptr<scalar_t>(),
                                   log_scales.data_ptr<scalar_t>(), keep.data_ptr<bool>(), n, int(threads),
                                   means2d.data_ptr<scalar_t>(), conics.data_ptr<scalar_t>(),
                                   depths.data_ptr<scalar_t>(), radii.data_ptr<int32_t>());
  });
  return {means2d, conics, depths, radii};
}

// Returns gradients: means [N,3], quats [N,4], log_scales [N,3], w2c [4,4] (rotation and translation rows).
std::vector<torch::Tensor> project_backward(torch::Tensor means, torch::Tensor quats, torch::Tensor log_scales,
                                            torch::Tensor K, torch::Tensor w2c, torch::Tensor radii,
                                            torch::Tensor g_m2d, torch::Tensor g_con, torch::Tensor g_z, int64_t width,
                                            int64_t height, double near, double eps2d, int64_t threads) {
  const int64_t n = means.size(0);
  check(g_m2d, "grad means2d", n, 2);
  check(g_con, "grad conics", n, 3);
  check(g_z, "grad depths", n, 0);
  const Camera cam = make_camera(K, w2c, width, height, near, eps2d);
  auto opts = means.options();
  auto d_means = torch::empty({n, 3}, opts), d_quats = torch::empty({n, 4}, opts);
  auto d_ls = torch::empty({n, 3}, opts);
  const int nt = std::max<int>(1, int(threads));
  // Per-Gaussian pose contributions, summed serially below so the result does not depend on the threads.
  auto d_Rt = torch::zeros({n, 12}, opts.dtype(torch::kDouble));
  AT_DISPATCH_FLOATING_TYPES(means.scalar_type(), "project_backward", [&] {
    project_backward_impl<scalar_t>(cam, means.data_ptr<scalar_t>(), quats.data_ptr<scalar_t>(),
                                    log_scales.data_ptr<scalar_t>(), radii.data_ptr<int32_t>(), n,
                                    g_m2d.data_ptr<scalar_t>(), g_con.data_ptr<scalar_t>(), g_z.data_ptr<scalar_t>(),
                                    nt, d_means.data_ptr<scalar_t>(), d_quats.data_ptr<scalar_t>(),
                                    d_ls.data_ptr<scalar_t>(), d_Rt.data_ptr<double>());
  });
  auto rt = torch::zeros({12}, opts.dtype(torch::kDouble));
  {
    const double* src = d_Rt.data_ptr<double>();
    double* dst = rt.data_ptr<double>();
    for (int64_t i = 0; i < n; ++i)
      for (int k = 0; k < 12; ++k) dst[k] += src[12 * i + k];
  }
  auto d_w2c = torch::zeros({4, 4}, opts.dtype(torch::kDouble));
  using torch::indexing::Slice;
  d_w2c.index_put_({Slice(0, 3), Slice(0, 3)}, rt.index({Slice(0, 9)}).reshape({3, 3}));
  d_w2c.index_put_({Slice(0, 3), 3}, rt.index({Slice(9, 12)}));
  return {d_means, d_quats, d_ls, d_w2c.to(w2c.scalar_type())};
}

PYBIND11_MODULE(TORCH_EXTENSION_NAME, m) {
  m.def("project_forward", &project_forward, "EWA projection forward (CPU)");
  m.def("project_backward", &project_backward, "EWA projection backward (CPU)");
  m.def("forward", &rasterize_forward, "Gaussian tile rasterizer forward (CPU)");
  m.def("backward", &rasterize_backward, "Gaussian tile rasterizer backward (CPU)");
}
