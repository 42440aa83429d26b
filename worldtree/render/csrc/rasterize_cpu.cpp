// Tile rasterizer for screen-space Gaussians on the CPU: forward and hand-written backward, OpenMP over tiles.
//
// Same image formation as worldtree/render/reference.py (the oracle): Gaussians binned into 16x16 tiles by
// their bounding square, front to back per tile (ties by index); per pixel alpha = min(0.99, o exp(power)),
// skipped when power > 0 or alpha < 1/255; compositing stops before T would fall below 1e-4.
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
Bins bin_gaussians(const T* means2d, const T* depths, const int32_t* radii, int64_t n, int width, int height) {
  const int tw = (width + TILE - 1) / TILE, th = (height + TILE - 1) / TILE;
  std::vector<int32_t> order;
  order.reserve(n);
  for (int64_t i = 0; i < n; ++i)
    if (radii[i] > 0) order.push_back(static_cast<int32_t>(i));
  std::stable_sort(order.begin(), order.end(), [&](int32_t a, int32_t b) { return depths[a] < depths[b]; });
  Bins bins;
  bins.count.assign(static_cast<size_t>(tw) * th, 0);
  std::vector<int> rect(order.size() * 4);
  for (size_t k = 0; k < order.size(); ++k) {
    const int32_t g = order[k];
    int* r = &rect[4 * k];
    tile_rect<T>(means2d[2 * g], means2d[2 * g + 1], static_cast<T>(radii[g]), tw, th, r[0], r[1], r[2], r[3]);
    for (int ty = r[2]; ty < r[3]; ++ty)
      for (int tx = r[0]; tx < r[1]; ++tx) bins.count[static_cast<size_t>(ty) * tw + tx]++;
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
      for (int tx = r[0]; tx < r[1]; ++tx) bins.ids[fill[static_cast<size_t>(ty) * tw + tx]++] = order[k];
  }
  return bins;
}

// Pixels of the tile outside which this Gaussian's alpha is certainly < 1/255 (with a one-pixel margin, so the
// exact per-pixel tests decide every borderline case). Returns false when no pixel can be reached.
template <typename T>
inline bool reach_box(T mx, T my, T a, T b, T c, T o, int px0, int px1, int py0, int py1, int& x0, int& x1, int& y0,
                      int& y1) {
  if (!(o >= Consts<T>::alpha_min)) return false;
  x0 = px0, x1 = px1, y0 = py0, y1 = py1;
  const double det = double(a) * double(c) - double(b) * double(b);
  const double L = 2.0 * std::log(255.0 * double(o));  // alpha >= 1/255 needs d^T C d <= L
  if (det > 0 && std::isfinite(det) && L >= 0) {
    const double ex = std::sqrt(L * double(c) / det) + 1.0, ey = std::sqrt(L * double(a) / det) + 1.0;
    if (std::isfinite(ex) && std::isfinite(ey)) {
      x0 = static_cast<int>(std::max<double>(px0, std::floor(double(mx) - ex)));
      x1 = static_cast<int>(std::min<double>(px1, std::ceil(double(mx) + ex) + 1.0));
      y0 = static_cast<int>(std::max<double>(py0, std::floor(double(my) - ey)));
      y1 = static_cast<int>(std::min<double>(py1, std::ceil(double(my) + ey) + 1.0));
    }
  }
  return x0 < x1 && y0 < y1;
}

// One row of a tile (16 pixels) is one GCC vector; the per-pixel loops below are written on whole rows, so
// they compile to SIMD instructions without relying on the auto-vectoriser. M is the matching lane mask.
template <typename T>
struct Row {
  typedef T V __attribute__((vector_size(TILE * sizeof(T))));
  typedef std::conditional_t<sizeof(T) == 4, int32_t, int64_t> I;
  typedef I M __attribute__((vector_size(TILE * sizeof(T))));
};

template <typename V, typename S>
inline V splat(S x) {
  V v = {};
  return v + static_cast<decltype(v[0] + 0)>(x);
}

template <typename V>
inline auto hsum(const V& v) {
  auto s = v[0];
  for (int i = 1; i < TILE; ++i) s += v[i];
  return s;
}

// exp on a row. float: Cody-Waite reduction and a degree-7 polynomial (about 2 ulp), branch-free SIMD.
// double (used by the tests): std::exp per lane.
inline Row<float>::V vexp(Row<float>::V x) {
  using V = Row<float>::V;
  using M = Row<float>::M;
  const V lo = splat<V>(-87.0f);  // below this exp underflows; such alphas are far under 1/255 anyway
  x = x < lo ? lo : x;
  const V kf = (x * 1.44269504088896341f + 12582912.0f) - 12582912.0f;  // round(x / ln 2)
  const V r = (x - kf * 0.693145751953125f) - kf * 1.428606765330187e-06f;
  V p = splat<V>(1.0f / 5040.0f);
  p = p * r + 1.0f / 720.0f;
  p = p * r + 1.0f / 120.0f;
  p = p * r + 1.0f / 24.0f;
  p = p * r + 1.0f / 6.0f;
  p = p * r + 0.5f;
  p = p * r + 1.0f;
  p = p * r + 1.0f;
  const M bits = (__builtin_convertvector(kf, M) + 127) << 23;
  return p * reinterpret_cast<const V&>(bits);
}
inline Row<double>::V vexp(Row<double>::V x) {
  for (int i = 0; i < TILE; ++i) x[i] = std::exp(x[i]);
  return x;
}

template <typename T>
void forward_impl(const T* means2d, const T* conics, const T* opac, const T* colors, const T* depths, const T* bg,
                  const Bins& bins, int width, int height, int threads, T* out_rgb, T* out_alpha, T* out_depth,
                  T* out_T, int32_t* out_last) {
  using V = typename Row<T>::V;
  using M = typename Row<T>::M;
  const int tw = (width + TILE - 1) / TILE, th = (height + TILE - 1) / TILE;
  const int n_tiles = tw * th;
  const V amax = splat<V>(Consts<T>::alpha_max), zero = splat<V>(0), one = splat<V>(1);
  const T amin = Consts<T>::alpha_min, tmin = Consts<T>::t_min;
#pragma omp parallel for schedule(dynamic, 1) num_threads(threads)
  for (int t = 0; t < n_tiles; ++t) {
    const int px0 = (t % tw) * TILE, py0 = (t / tw) * TILE;
    const int px1 = std::min(px0 + TILE, width), py1 = std::min(py0 + TILE, height);
    const int n_pix = (px1 - px0) * (py1 - py0);
    // Per row: transmittance, accumulated r, g, b, depth, index+1 of the last composited Gaussian (as T:
    // exact below 2^24 per tile, checked by the caller), and a finished flag.
    V Tr[TILE], ar[TILE], ag[TILE], ab[TILE], az[TILE], last[TILE], done[TILE];
    V xs;
    for (int i = 0; i < TILE; ++i) xs[i] = T(px0 + i);
    for (int r = 0; r < TILE; ++r) {
      Tr[r] = one;
      ar[r] = ag[r] = ab[r] = az[r] = last[r] = zero;
      // Pixels of a partial tile that lie outside the image are born finished.
      for (int i = 0; i < TILE; ++i) done[r][i] = (px0 + i < px1 && py0 + r < py1) ? T(0) : T(1);
    }
    M stopped = splat<M>(0);  // lanes hold -(number of pixels of that column that finished)
    const int64_t s = bins.start[t], cnt = bins.count[t];
    for (int64_t k = 0; k < cnt; ++k) {
      const int32_t g = bins.ids[s + k];
      const T mx = means2d[2 * g], my = means2d[2 * g + 1];
      const T ca = conics[3 * g], cb = conics[3 * g + 1], cc = conics[3 * g + 2];
      const T o = opac[g];
      int x0, x1, y0, y1;
      if (!reach_box<T>(mx, my, ca, cb, cc, o, px0, px1, py0, py1, x0, x1, y0, y1)) continue;
      const T cr = colors[3 * g], cg = colors[3 * g + 1], cbl = colors[3 * g + 2], z = depths[g];
      const V kk = splat<V>(k + 1);
      const V dx = xs - mx;
      const V cdx = ca * dx * dx;
      for (int y = y0; y < y1; ++y) {
        const int r = y - py0;
        const T dy = T(y) - my;
        const V power = T(-0.5) * (cdx + cc * dy * dy) - cb * dx * dy;
        V alpha = o * vexp(power);
        alpha = alpha < amax ? alpha : amax;
        const M ok = (done[r] == T(0)) & (power <= T(0)) & (alpha >= amin);
        const V next = Tr[r] * (T(1) - alpha);
        const M stop = ok & (next < tmin);
        const M use = ok & ~stop;
        const V w = use ? alpha * Tr[r] : zero;
        ar[r] += w * cr;
        ag[r] += w * cg;
        ab[r] += w * cbl;
        az[r] += w * z;
        Tr[r] = use ? next : Tr[r];
        last[r] = use ? kk : last[r];
        done[r] = stop ? one : done[r];
        stopped += stop;
      }
      if (-hsum(stopped) >= n_pix) break;
    }
    for (int y = py0; y < py1; ++y)
      for (int x = px0; x < px1; ++x) {
        const int r = y - py0, i = x - px0;
        const int64_t q = static_cast<int64_t>(y) * width + x;
        const T tr = Tr[r][i];
        out_rgb[3 * q] = ar[r][i] + tr * bg[0];
        out_rgb[3 * q + 1] = ag[r][i] + tr * bg[1];
        out_rgb[3 * q + 2] = ab[r][i] + tr * bg[2];
        out_alpha[q] = T(1) - tr;
        out_depth[q] = az[r][i];
        out_T[q] = tr;
        out_last[q] = static_cast<int32_t>(last[r][i]);
      }
  }
}

template <typename T>
void backward_impl(const T* means2d, const T* conics, const T* opac, const T* colors, const T* depths, const T* bg,
                   const int32_t* ids, const int64_t* tstart, const int64_t* tcount, const T* final_T,
                   const int32_t* last_in, const T* g_rgb, const T* g_alpha, const T* g_depth, int width, int height,
                   int threads, T* pair_grad) {
  using V = typename Row<T>::V;
  using M = typename Row<T>::M;
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
    // Per row: Tr = transmittance behind the Gaussians still to visit; B* = normalised colour behind them
    // (r, g, b, depth, alpha channel); G* = dL/d(output); last = composited count (pixels outside: 0).
    V Tr[TILE], Br[TILE], Bg[TILE], Bb[TILE], Bz[TILE], Ba[TILE];
    V Gr[TILE], Gg[TILE], Gb[TILE], Gz[TILE], Ga[TILE], last[TILE];
    V xs;
    for (int i = 0; i < TILE; ++i) xs[i] = T(px0 + i);
    for (int r = 0; r < TILE; ++r) {
      Tr[r] = splat<V>(1);
      Br[r] = splat<V>(bg[0]), Bg[r] = splat<V>(bg[1]), Bb[r] = splat<V>(bg[2]);
      Bz[r] = Ba[r] = Gr[r] = Gg[r] = Gb[r] = Gz[r] = Ga[r] = last[r] = zero;
    }
    int32_t max_last = 0;
    for (int y = py0; y < py1; ++y)
      for (int x = px0; x < px1; ++x) {
        const int r = y - py0, i = x - px0;
        const int64_t q = static_cast<int64_t>(y) * width + x;
        Tr[r][i] = final_T[q];
        last[r][i] = T(last_in[q]);
        max_last = std::max(max_last, last_in[q]);
        Gr[r][i] = g_rgb[3 * q], Gg[r][i] = g_rgb[3 * q + 1], Gb[r][i] = g_rgb[3 * q + 2];
        Gz[r][i] = g_depth[q], Ga[r][i] = g_alpha[q];
      }
    for (int64_t k = max_last - 1; k >= 0; --k) {
      const int32_t g = ids[s + k];
      const T mx = means2d[2 * g], my = means2d[2 * g + 1];
      const T ca = conics[3 * g], cb = conics[3 * g + 1], cc = conics[3 * g + 2];
      const T o = opac[g];
      int x0, x1, y0, y1;
      if (!reach_box<T>(mx, my, ca, cb, cc, o, px0, px1, py0, py1, x0, x1, y0, y1)) continue;
      const T cr = colors[3 * g], cg = colors[3 * g + 1], cbl = colors[3 * g + 2], z = depths[g];
      const V kk = splat<V>(k);
      const V dx = xs - mx;
      const V cdx = ca * dx * dx;
      V d_mx = zero, d_my = zero, d_a = zero, d_b = zero, d_c = zero, d_o = zero;
      V d_r = zero, d_g = zero, d_bl = zero, d_z = zero;
      for (int y = y0; y < y1; ++y) {
        const int r = y - py0;
        const T dy = T(y) - my;
        const V power = T(-0.5) * (cdx + cc * dy * dy) - cb * dx * dy;
        const V gauss = vexp(power);
        const V raw = o * gauss;
        const V alpha = raw < amax ? raw : amax;
        const M active = (kk < last[r]) & (power <= T(0)) & (alpha >= amin);
        const V t_k = Tr[r] / (T(1) - alpha);  // transmittance in front of this Gaussian
        const V w = active ? alpha * t_k : zero;
        d_r += w * Gr[r];
        d_g += w * Gg[r];
        d_bl += w * Gb[r];
        d_z += w * Gz[r];
        V d_alpha = Gr[r] * (cr - Br[r]) + Gg[r] * (cg - Bg[r]) + Gb[r] * (cbl - Bb[r]) + Gz[r] * (z - Bz[r]) +
                    Ga[r] * (T(1) - Ba[r]);
        d_alpha = (active & (raw <= amax)) ? d_alpha * t_k : zero;  // clamped alpha: no gradient
        const V keep = T(1) - alpha;
        Br[r] = active ? alpha * cr + keep * Br[r] : Br[r];
        Bg[r] = active ? alpha * cg + keep * Bg[r] : Bg[r];
        Bb[r] = active ? alpha * cbl + keep * Bb[r] : Bb[r];
        Bz[r] = active ? alpha * z + keep * Bz[r] : Bz[r];
        Ba[r] = active ? alpha + keep * Ba[r] : Ba[r];
        Tr[r] = active ? t_k : Tr[r];
        d_o += gauss * d_alpha;
        const V d_pow = raw * d_alpha;
        d_a += T(-0.5) * dx * dx * d_pow;
        d_c += T(-0.5) * dy * dy * d_pow;
        d_b += -dx * dy * d_pow;
        d_mx += (ca * dx + cb * dy) * d_pow;
        d_my += (cb * dx + cc * dy) * d_pow;
      }
      T* slot = pair_grad + (s + k) * NGRAD;
      slot[0] = hsum(d_mx), slot[1] = hsum(d_my), slot[2] = hsum(d_a), slot[3] = hsum(d_b), slot[4] = hsum(d_c);
      slot[5] = hsum(d_o), slot[6] = hsum(d_r), slot[7] = hsum(d_g), slot[8] = hsum(d_bl), slot[9] = hsum(d_z);
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
// tile_start [n_tiles] int64, tile_count [n_tiles] int64.
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
  torch::Tensor ids, tstart, tcount;
  AT_DISPATCH_FLOATING_TYPES(means2d.scalar_type(), "rasterize_forward", [&] {
    Bins bins = bin_gaussians<scalar_t>(means2d.data_ptr<scalar_t>(), depths.data_ptr<scalar_t>(),
                                        radii.data_ptr<int32_t>(), n, int(width), int(height));
    for (int64_t c : bins.count)
      TORCH_CHECK(c < (int64_t(1) << 24), "more than 2^24 Gaussians in one tile; use the reference backend");
    forward_impl<scalar_t>(means2d.data_ptr<scalar_t>(), conics.data_ptr<scalar_t>(), opac.data_ptr<scalar_t>(),
                           colors.data_ptr<scalar_t>(), depths.data_ptr<scalar_t>(), bg.data_ptr<scalar_t>(), bins,
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
  return {rgb, alpha, depth, final_T, last, ids, tstart, tcount};
}

// Returns gradients: means2d [N,2], conics [N,3], opacities [N], colors [N,3], depths [N].
std::vector<torch::Tensor> rasterize_backward(torch::Tensor means2d, torch::Tensor conics, torch::Tensor opac,
                                              torch::Tensor colors, torch::Tensor depths, torch::Tensor bg,
                                              torch::Tensor ids, torch::Tensor tstart, torch::Tensor tcount,
                                              torch::Tensor final_T, torch::Tensor last, torch::Tensor g_rgb,
                                              torch::Tensor g_alpha, torch::Tensor g_depth, int64_t width,
                                              int64_t height, int64_t threads) {
  const int64_t n = means2d.size(0), m = ids.size(0);
  TORCH_CHECK(g_rgb.is_contiguous() && g_alpha.is_contiguous() && g_depth.is_contiguous(),
              "output gradients must be contiguous");
  auto opts = means2d.options();
  auto pair_grad = torch::zeros({m, NGRAD}, opts);
  auto grad = torch::zeros({n, NGRAD}, opts);
  AT_DISPATCH_FLOATING_TYPES(means2d.scalar_type(), "rasterize_backward", [&] {
    backward_impl<scalar_t>(means2d.data_ptr<scalar_t>(), conics.data_ptr<scalar_t>(), opac.data_ptr<scalar_t>(),
                            colors.data_ptr<scalar_t>(), depths.data_ptr<scalar_t>(), bg.data_ptr<scalar_t>(),
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

PYBIND11_MODULE(TORCH_EXTENSION_NAME, m) {
  m.def("forward", &rasterize_forward, "Gaussian tile rasterizer forward (CPU)");
  m.def("backward", &rasterize_backward, "Gaussian tile rasterizer backward (CPU)");
}
