#pragma once

// Least squares matching (LSM) of one patch: where a template point lands in the base image,
// with the local affine distortion around it. Two methods behind one interface:
//  - kFast (FLSM, the paper's section 4): the LSM equation is projected onto the 7 steerable
//    basis filters of Freeman & Adelson (G2: 3, H2: 4) at 3 scales, giving 21 equations for the
//    6 affine unknowns (+ 1 gain), solved by inverse-compositional Gauss-Newton.
//  - kTraditional (TLSM, Gruen 1985): one equation per pixel of a square window, forward
//    compositional Gauss-Newton with the gradients of the re-warped base patch, the baseline.
//
// Usage:
//   LsmMatcher matcher;                                  // builds the filter bank once
//   LsmResult r = matcher.Match(base_f32, templ_f32, p_in_template, p_in_base_initial);
//   if (r.ok()) tie = {p_in_template, r.position_in_base};
//
// Geometry: a template pixel p + x (x relative to the key point p) maps to base pixel
// position_in_base + base_from_template_linear * x.

#include <Eigen/Core>
#include <opencv2/core.hpp>
#include <string>
#include <vector>

#include "irmosaic/export.h"

namespace irmosaic {

enum class LsmMethod { kFast, kTraditional };

struct LsmOptions {
  LsmMethod method = LsmMethod::kFast;
  // FLSM filter scales. A filter of scale s is sampled at x = u / s, y = v / s for pixel
  // offsets (u, v), i.e. its Gaussian envelope exp(-(x^2 + y^2)) has a standard deviation of
  // s / sqrt(2) pixels (docs/matching.md, "Fine registration").
  std::vector<double> scales_px = {7.0, 9.0, 11.0};
  // Patch half-size in units of the largest scale. At 2 the envelope is down to 0.018 and the
  // (re-zeroed) filters keep most of their energy, while the patch (45 px for scale 11)
  // still fits in a 15 % overlap strip of a 512-px frame.
  double support_in_scales = 2.0;
  // TLSM window half-size in pixels (0: the FLSM patch half-size).
  int tlsm_radius_px = 0;
  int max_iterations = 20;
  // Iterations (at most) that move the translation only before the affine is freed; they end
  // early once the translation has converged. 0: full affine from the start.
  int translation_only_iterations = 5;
  // Estimate the 4 linear affine terms; false keeps the initial linear part (translation and
  // gain only), steadier under heavy noise when the initial affine is already close.
  bool estimate_affine = true;
  // Converged when an update moves every patch corner by less than this (pixels).
  double convergence_px = 0.005;
  // Diverged when the point moves further than this from its start (pixels) ...
  double max_shift_px = 6.0;
  // ... or the local affine leaves identity by more than this (any entry of A - I).
  double max_affine_deviation = 0.25;
  // Ill-conditioned when the column-normalised system's condition number exceeds this.
  double max_condition = 1.0e3;
  // Too little texture when the a-posteriori standard deviation of the position exceeds this.
  double max_position_sigma_px = 0.5;
  // Estimate a radiometric gain (FLSM's zero-mean filters cancel offsets by themselves; TLSM
  // also estimates an offset). Cameras change gain between frames.
  bool estimate_gain = true;

  // False with a message when an option is out of range.
  bool IsValid(std::string* error) const;
};

struct LsmResult {
  enum class Status {
    kConverged,       // Update below convergence_px within max_iterations.
    kNotConverged,    // Still moving after max_iterations (result kept, not trusted).
    kDiverged,        // Left max_shift_px / max_affine_deviation or the gain went absurd.
    kLowTexture,      // Flat patch or position sigma above max_position_sigma_px.
    kIllConditioned,  // System condition number above max_condition.
    kOutOfBounds,     // The patch left the template or base image.
    kBadInput,        // Wrong image type, empty image, non-finite point.
  };
  Status status = Status::kBadInput;
  std::string reason;
  Eigen::Vector2d position_in_base = Eigen::Vector2d::Zero();  // Tie point in base pixels.
  Eigen::Matrix2d base_from_template_linear = Eigen::Matrix2d::Identity();  // Local affine A.
  int iterations = 0;
  double gain = 1.0;               // Base intensity / template intensity.
  double condition = 0.0;          // Condition number of the column-normalised system.
  double position_sigma_px = 0.0;  // A-posteriori std of the position (larger axis).
  double residual_rms = 0.0;       // RMS of the final equation residuals (gray levels).

  bool ok() const { return status == Status::kConverged; }
};

// Human-readable name of a status ("converged", "diverged", ...).
IRMOSAIC_EXPORT const char* ToString(LsmResult::Status status);

// The 7 Freeman-Adelson basis filters (G2a, G2b, G2c, H2a, H2b, H2c, H2d) sampled at scale
// `scale_px` on a (2 radius + 1)^2 grid, CV_64F. With `zero_mean`, a multiple of the Gaussian
// envelope is removed from each so its samples sum to exactly zero (an intensity offset then
// cancels) and each is scaled to unit L2 norm.
IRMOSAIC_EXPORT std::vector<cv::Mat> SteerableBasisFilters(double scale_px, int radius_px,
                                                           bool zero_mean);

// Matches patches; holds the filter bank and scratch buffers, so reuse one per thread.
class IRMOSAIC_EXPORT LsmMatcher {
 public:
  // Throws InputError when the options are invalid.
  explicit LsmMatcher(LsmOptions options = {});

  // Refines where template pixel `point_in_template` lands in `base`, starting at
  // `initial_in_base` with local affine `initial_linear`. Both images CV_32FC1 (the caller
  // converts once per image, not per patch).
  LsmResult Match(const cv::Mat& base, const cv::Mat& templ,
                  const Eigen::Vector2d& point_in_template, const Eigen::Vector2d& initial_in_base,
                  const Eigen::Matrix2d& initial_linear = Eigen::Matrix2d::Identity());

  // As Match, FLSM method only, from the template's projections at the point (what
  // ProjectTemplate gives): a caller that also needs them for a joint solve computes them once.
  LsmResult MatchProjected(const cv::Mat& base, const Eigen::MatrixXd& projected,
                           const Eigen::Vector2d& initial_in_base,
                           const Eigen::Matrix2d& initial_linear = Eigen::Matrix2d::Identity());

  // FLSM building blocks for a joint solve over many patches (FLSM method only):
  // the 21 x 7 filter projections of the template design images [Ix, x Ix, y Ix, Iy, x Iy,
  // y Iy, I] around p (x, y in units of the patch half-size); false when out of bounds.
  bool ProjectTemplate(const cv::Mat& templ, const Eigen::Vector2d& p, Eigen::MatrixXd* projected);
  // The 21 filter responses of `base` sampled at c + M x; false when out of bounds.
  bool ProjectBase(const cv::Mat& base, const Eigen::Vector2d& c, const Eigen::Matrix2d& m,
                   Eigen::VectorXd* responses);

  // Half-size of the template patch the chosen method reads (pixels); key points must lie at
  // least this far (+1 for gradients) inside the valid areas.
  int patch_radius_px() const { return radius_; }
  const LsmOptions& options() const { return options_; }

 private:
  LsmResult MatchFast(const cv::Mat& base, const cv::Mat& templ, const Eigen::Vector2d& p,
                      const Eigen::Vector2d& c0, const Eigen::Matrix2d& m0);
  LsmResult MatchFastProjected(const cv::Mat& base, const Eigen::MatrixXd& projected,
                               const Eigen::Vector2d& c0, const Eigen::Matrix2d& m0);
  LsmResult MatchTraditional(const cv::Mat& base, const cv::Mat& templ, const Eigen::Vector2d& p,
                             const Eigen::Vector2d& c0, const Eigen::Matrix2d& m0);
  // Samples base at c + M x for the patch grid x into `out` ((2r+1)^2, CV_32F); false when
  // any sample falls outside the base image.
  bool WarpPatch(const cv::Mat& base, const Eigen::Vector2d& c, const Eigen::Matrix2d& m, int r,
                 cv::Mat* out);

  LsmOptions options_;
  int radius_ = 0;
  // FLSM: 21 filters, one row each, over the (2 radius_ + 1)^2 patch (row-major pixels).
  Eigen::Matrix<float, Eigen::Dynamic, Eigen::Dynamic, Eigen::RowMajor> bank_;
  cv::Mat warped_, rows_;  // Scratch.
};

}  // namespace irmosaic
