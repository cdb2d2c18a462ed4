#pragma once
// Private helper of the registration (src/lsm.cc, src/registration.cc): the bicubic kernel both
// warp their patches with, so the single-patch and the joint fits interpolate alike. Not
// installed.

namespace irmosaic {

// Keys (a = -0.5) cubic interpolation weights for a fractional offset t in [0, 1).
inline void CubicWeights(float t, float* w) {
  const float t2 = t * t, t3 = t2 * t;
  w[0] = -0.5f * t3 + t2 - 0.5f * t;
  w[1] = 1.5f * t3 - 2.5f * t2 + 1.0f;
  w[2] = -1.5f * t3 + 2.0f * t2 + 0.5f * t;
  w[3] = 0.5f * t3 - 0.5f * t2;
}

}  // namespace irmosaic
