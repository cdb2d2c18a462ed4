#pragma once
// Private to the map fusion (src/map_fusion.cc): the window optimizer's homography update and
// its cost functions, with analytic Jacobians. With autodiff (ceres::Jet<double, 16> through
// both homographies of a tie) residual evaluation was about two thirds of the optimizer's CPU
// time; the update is linear in the 8 parameters, so its Jacobian is a few products. Not
// installed; tests/map_fusion_test.cc checks the costs against autodiff of the original form.
// The solve uses PairTieCost (a pair's ties in one block) and PriorCost; TieCost is the one-tie
// form the tests hold PairTieCost to.

#include <ceres/cost_function.h>
#include <ceres/sized_cost_function.h>

#include <Eigen/Core>
#include <array>
#include <cmath>
#include <vector>

namespace irmosaic::fusion {

// Image-point normalization for the homography update: n = (p - c) / s, so the 8 update
// parameters have comparable scales (pixel coordinates would make the projective ones tiny).
struct Normalizer {
  double cx = 0.0, cy = 0.0, s = 1.0;

  // S: image px -> normalized, and its inverse.
  Eigen::Matrix3d NormalizedFromImage() const {
    Eigen::Matrix3d m;
    m << 1.0 / s, 0, -cx / s, 0, 1.0 / s, -cy / s, 0, 0, 1;
    return m;
  }
  Eigen::Matrix3d ImageFromNormalized() const {
    Eigen::Matrix3d m;
    m << s, 0, cx, 0, s, cy, 0, 0, 1;
    return m;
  }
  Eigen::Vector2d Normalize(const Eigen::Vector2d& image_px) const {
    return {(image_px.x() - cx) / s, (image_px.y() - cy) / s};
  }
};

// The placement after an update: mosaic_from_image * S^-1 * U(delta) * S, scaled to h(2,2) = 1
// (the scale does not move mapped points), U(delta) = I + [d0 d1 d2; d3 d4 d5; d6 d7 0].
inline Eigen::Matrix3d ApplyDelta(const Eigen::Matrix3d& mosaic_from_image, const Normalizer& n,
                                  const double* delta) {
  Eigen::Matrix3d update;
  update << 1 + delta[0], delta[1], delta[2], delta[3], 1 + delta[4], delta[5], delta[6], delta[7],
      1;
  Eigen::Matrix3d h =
      mosaic_from_image * n.ImageFromNormalized() * update * n.NormalizedFromImage();
  return h / h(2, 2);
}

// Mosaic position of a normalized point p under mosaic_from_normalized * U(delta), times
// `scale`; with `jacobian` (2x8 row-major, may be null) its derivative in delta, times `scale`.
// u = U(delta) (p, 1) is linear in delta, v = M u, q = v.xy / v.z, so
// dq/dd = (1 / v.z) [M.row0 - q.x M.row2; M.row1 - q.y M.row2] du/dd, where du/dd has
// (p.x, p.y, 1) in row 0 (d0..d2), in row 1 (d3..d5) and (p.x, p.y) in row 2 (d6, d7).
inline void MapNormalized(const Eigen::Matrix3d& mosaic_from_normalized, const Eigen::Vector2d& p,
                          const double* delta, double scale, double* mosaic_px, double* jacobian) {
  const Eigen::Matrix3d& m = mosaic_from_normalized;
  const double u0 = p.x() + delta[0] * p.x() + delta[1] * p.y() + delta[2];
  const double u1 = delta[3] * p.x() + p.y() + delta[4] * p.y() + delta[5];
  const double u2 = delta[6] * p.x() + delta[7] * p.y() + 1.0;
  const double v0 = m(0, 0) * u0 + m(0, 1) * u1 + m(0, 2) * u2;
  const double v1 = m(1, 0) * u0 + m(1, 1) * u1 + m(1, 2) * u2;
  const double v2 = m(2, 0) * u0 + m(2, 1) * u1 + m(2, 2) * u2;
  const double inv_w = 1.0 / v2;
  const double qx = v0 * inv_w, qy = v1 * inv_w;
  mosaic_px[0] = qx * scale;
  mosaic_px[1] = qy * scale;
  if (jacobian == nullptr) return;
  const double g = inv_w * scale;
  for (int r = 0; r < 2; ++r) {
    const double q = r == 0 ? qx : qy;
    double* row = jacobian + 8 * r;
    // dq_r/du = g (M.row_r - q_r M.row2), spread over the parameters u depends on.
    const double du0 = g * (m(r, 0) - q * m(2, 0));
    const double du1 = g * (m(r, 1) - q * m(2, 1));
    const double du2 = g * (m(r, 2) - q * m(2, 2));
    row[0] = du0 * p.x();
    row[1] = du0 * p.y();
    row[2] = du0;
    row[3] = du1 * p.x();
    row[4] = du1 * p.y();
    row[5] = du1;
    row[6] = du2 * p.x();
    row[7] = du2 * p.y();
  }
}

// A tie point: both frames' placements should put it at the same mosaic pixel. Residual
// (q_a - q_b) / sigma, mosaic px in units of the tie's sigma; parameters delta_a, delta_b.
// (The solve holds a pair's ties in one PairTieCost; this is one tie's residual, for tests.)
class TieCost final : public ceres::SizedCostFunction<2, 8, 8> {
 public:
  TieCost(const Eigen::Matrix3d& mosaic_from_image_a, const Eigen::Matrix3d& mosaic_from_image_b,
          const Normalizer& n, const Eigen::Vector2d& image_px_a, const Eigen::Vector2d& image_px_b,
          double inv_sigma)
      : mosaic_from_normalized_a_(mosaic_from_image_a * n.ImageFromNormalized()),
        mosaic_from_normalized_b_(mosaic_from_image_b * n.ImageFromNormalized()),
        normalized_a_(n.Normalize(image_px_a)),
        normalized_b_(n.Normalize(image_px_b)),
        inv_sigma_(inv_sigma) {}

  bool Evaluate(double const* const* parameters, double* residuals,
                double** jacobians) const override {
    double qa[2], qb[2];
    MapNormalized(mosaic_from_normalized_a_, normalized_a_, parameters[0], inv_sigma_, qa,
                  jacobians ? jacobians[0] : nullptr);
    MapNormalized(mosaic_from_normalized_b_, normalized_b_, parameters[1], -inv_sigma_, qb,
                  jacobians ? jacobians[1] : nullptr);
    // qb carries -1 / sigma, so the residual is a sum.
    residuals[0] = qa[0] + qb[0];
    residuals[1] = qa[1] + qb[1];
    return true;
  }

 private:
  Eigen::Matrix3d mosaic_from_normalized_a_, mosaic_from_normalized_b_;  // H * S^-1.
  Eigen::Vector2d normalized_a_, normalized_b_;                          // S * p.
  double inv_sigma_;
};

// The robust weighting of one tie: rho(s) of its squared whitened residual s, the pair's
// weight w times s (least squares) or times b^2 log(1 + s / b^2) / s (Cauchy of scale b), as
// ceres::ScaledLoss(w) over nothing or over ceres::CauchyLoss(b).
struct TieLoss {
  double weight = 1.0;
  double cauchy_scale = 0.0;  // b; 0: least squares.
};

// rho(s) / s of `loss` and its derivative in s. Near s = 0 the series (log1p(x) / x and its
// derivative lose digits there).
inline void RobustRatio(const TieLoss& loss, double s, double* g, double* dg) {
  if (loss.cauchy_scale <= 0.0) {
    *g = loss.weight;
    *dg = 0.0;
    return;
  }
  const double b2 = loss.cauchy_scale * loss.cauchy_scale;
  const double x = s / b2;
  if (x < 1e-4) {
    // log1p(x) / x = 1 - x / 2 + x^2 / 3 - ...; its derivative -1/2 + 2 x / 3 - ..., in s / b^2.
    *g = loss.weight * (1.0 - x / 2.0 + x * x / 3.0);
    *dg = loss.weight * (-0.5 + 2.0 * x / 3.0) / b2;
    return;
  }
  const double log_term = std::log1p(x);
  *g = loss.weight * log_term / x;
  *dg = loss.weight * (1.0 / (1.0 + x) - log_term / x) / (x * b2);
}

// All tie points of one pair in one residual block: 2 values per tie, each tie's residual r
// (TieCost's) scaled by sqrt(rho(s) / s), s = |r|^2, so that the block's squared norm is the sum
// of rho(s) over its ties: the objective of one TieCost per tie under the loss, with one block
// instead of one per tie (Ceres' per-block work, the Jacobian's product terms and their
// sorting, was most of a solve). The Jacobian is exact for that scaled residual:
// sqrt(g) J + (g' / sqrt(g)) r r^T J, g = rho(s) / s; its gradient is rho'(s) J^T r, as Ceres'
// own loss correction gives. The loss is read at each evaluation, so a solve may change it
// between stages.
class PairTieCost final : public ceres::CostFunction {
 public:
  PairTieCost(const Eigen::Matrix3d& mosaic_from_image_a,
              const Eigen::Matrix3d& mosaic_from_image_b, const Normalizer& n,
              const std::vector<Eigen::Vector2d>& image_px_a,
              const std::vector<Eigen::Vector2d>& image_px_b, double inv_sigma, const TieLoss* loss)
      : mosaic_from_normalized_a_(mosaic_from_image_a * n.ImageFromNormalized()),
        mosaic_from_normalized_b_(mosaic_from_image_b * n.ImageFromNormalized()),
        inv_sigma_(inv_sigma),
        loss_(loss) {
    normalized_a_.reserve(image_px_a.size());
    normalized_b_.reserve(image_px_b.size());
    for (const Eigen::Vector2d& p : image_px_a) normalized_a_.push_back(n.Normalize(p));
    for (const Eigen::Vector2d& p : image_px_b) normalized_b_.push_back(n.Normalize(p));
    set_num_residuals(static_cast<int>(2 * normalized_a_.size()));
    mutable_parameter_block_sizes()->assign({8, 8});
  }

  bool Evaluate(double const* const* parameters, double* residuals,
                double** jacobians) const override {
    double* ja_all = jacobians ? jacobians[0] : nullptr;
    double* jb_all = jacobians ? jacobians[1] : nullptr;
    for (size_t t = 0; t < normalized_a_.size(); ++t) {
      double qa[2], qb[2];
      double* ja = ja_all ? ja_all + 16 * t : nullptr;
      double* jb = jb_all ? jb_all + 16 * t : nullptr;
      MapNormalized(mosaic_from_normalized_a_, normalized_a_[t], parameters[0], inv_sigma_, qa, ja);
      MapNormalized(mosaic_from_normalized_b_, normalized_b_[t], parameters[1], -inv_sigma_, qb,
                    jb);
      const double r0 = qa[0] + qb[0], r1 = qa[1] + qb[1];
      double g, dg;
      RobustRatio(*loss_, r0 * r0 + r1 * r1, &g, &dg);
      const double root = std::sqrt(g);
      residuals[2 * t] = root * r0;
      residuals[2 * t + 1] = root * r1;
      const double k = dg / root;
      for (double* j : {ja, jb}) {
        if (j == nullptr) continue;
        for (int c = 0; c < 8; ++c) {
          const double rj = r0 * j[c] + r1 * j[8 + c];  // r^T J, column c.
          j[c] = root * j[c] + k * r0 * rj;
          j[8 + c] = root * j[8 + c] + k * r1 * rj;
        }
      }
    }
    return true;
  }

 private:
  Eigen::Matrix3d mosaic_from_normalized_a_, mosaic_from_normalized_b_;  // H * S^-1.
  std::vector<Eigen::Vector2d> normalized_a_, normalized_b_;             // S * p.
  double inv_sigma_;
  const TieLoss* loss_;
};

// POS prior: the frame's corners and centre stay near where POS puts them, whitened by the
// square-root information of the POS error (FusionFrame::prior_sqrt_information; its lower
// triangle). POS errors move a footprint mostly as a whole and barely change its shape; tie
// points in a narrow overlap strip cannot fix a frame's shape, so an isotropic prior leaves
// the network floppy. Residual L (q - target), 10 values; parameters delta.
class PriorCost final : public ceres::SizedCostFunction<10, 8> {
 public:
  PriorCost(const Eigen::Matrix3d& mosaic_from_image, const Normalizer& n,
            const std::array<Eigen::Vector2d, 5>& image_px,
            const Eigen::Matrix<double, 10, 1>& target_mosaic_px,
            const Eigen::Matrix<double, 10, 10>& sqrt_information)
      : mosaic_from_normalized_(mosaic_from_image * n.ImageFromNormalized()),
        target_mosaic_px_(target_mosaic_px),
        sqrt_information_(sqrt_information.triangularView<Eigen::Lower>()) {
    for (int k = 0; k < 5; ++k) normalized_[k] = n.Normalize(image_px[k]);
  }

  bool Evaluate(double const* const* parameters, double* residuals,
                double** jacobians) const override {
    Eigen::Matrix<double, 10, 1> error;
    Eigen::Matrix<double, 10, 8, Eigen::RowMajor> d_error;
    double* d_error_rows = jacobians && jacobians[0] ? d_error.data() : nullptr;
    for (int k = 0; k < 5; ++k) {
      MapNormalized(mosaic_from_normalized_, normalized_[k], parameters[0], 1.0,
                    error.data() + 2 * k, d_error_rows ? d_error_rows + 16 * k : nullptr);
    }
    error -= target_mosaic_px_;
    Eigen::Map<Eigen::Matrix<double, 10, 1>> whitened(residuals);
    whitened.noalias() = sqrt_information_.triangularView<Eigen::Lower>() * error;
    if (d_error_rows) {
      Eigen::Map<Eigen::Matrix<double, 10, 8, Eigen::RowMajor>> d_whitened(jacobians[0]);
      d_whitened.noalias() = sqrt_information_.triangularView<Eigen::Lower>() * d_error;
    }
    return true;
  }

 private:
  Eigen::Matrix3d mosaic_from_normalized_;
  std::array<Eigen::Vector2d, 5> normalized_;  // Four corners, then the centre; S * p.
  Eigen::Matrix<double, 10, 1> target_mosaic_px_;
  Eigen::Matrix<double, 10, 10> sqrt_information_;  // Lower triangle; zero above.
};

}  // namespace irmosaic::fusion
