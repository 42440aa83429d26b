// Quaternion and vector arithmetic in double shared by the motion kernels that work one entry at a time
// (relative_cpu.cpp, smooth_cpu.cpp): the Hamilton product, the conjugate, the cross and dot products, and the
// normalisation of quaternion.normalize with its gradient. Included once by motion_cpu.cpp, before those files.
#pragma once

#include <cmath>

namespace motion_quat {

struct Quat {
  double w, x, y, z;
};
struct Vec {
  double x, y, z;
};

inline Quat mul(const Quat& a, const Quat& b) {  // Hamilton product a b
  return {a.w * b.w - a.x * b.x - a.y * b.y - a.z * b.z, a.w * b.x + a.x * b.w + a.y * b.z - a.z * b.y,
          a.w * b.y - a.x * b.z + a.y * b.w + a.z * b.x, a.w * b.z + a.x * b.y - a.y * b.x + a.z * b.w};
}
inline Quat conj(const Quat& q) { return {q.w, -q.x, -q.y, -q.z}; }
inline Vec cross(const Vec& a, const Vec& b) {
  return {a.y * b.z - a.z * b.y, a.z * b.x - a.x * b.z, a.x * b.y - a.y * b.x};
}
inline double dot(const Vec& a, const Vec& b) { return a.x * b.x + a.y * b.y + a.z * b.z; }
inline double dot(const Quat& a, const Quat& b) { return a.w * b.w + a.x * b.x + a.y * b.y + a.z * b.z; }
inline Vec vec(const Quat& q) { return {q.x, q.y, q.z}; }
inline Quat load(const float* q) { return {q[0], q[1], q[2], q[3]}; }

// q / |q| and 1 / |q| (*inv_norm); the identity and 0 where |q|^2 <= eps^2 or is NaN, as quaternion.normalize.
inline Quat unit(const Quat& q, double eps2, double* inv_norm) {
  const double n2 = dot(q, q);
  if (!(n2 > eps2)) {
    *inv_norm = 0.0;
    return {1.0, 0.0, 0.0, 0.0};
  }
  const double inv = 1.0 / std::sqrt(n2);
  *inv_norm = inv;
  return {q.w * inv, q.x * inv, q.y * inv, q.z * inv};
}

// Gradient through q -> q / |q| at the unit value n (inv = 1 / |q|, 0 for the identity fallback): (g - n (n.g)) inv.
inline Quat unit_grad(const Quat& n, const Quat& g, double inv) {
  const double d = dot(n, g);
  return {(g.w - n.w * d) * inv, (g.x - n.x * d) * inv, (g.y - n.y * d) * inv, (g.z - n.z * d) * inv};
}

}  // namespace motion_quat
