#pragma once

// Fine registration of an image pair (paper section 4.3): key points in the overlap, least
// squares matching at each (fast LSM by default) from a coarse translation, tie points, and a
// RANSAC homography with quality figures and documented accept criteria.
//
// Usage (coarse translation known, e.g. from SCD):
//   FineRegistrar registrar;                  // one per thread; reuse across pairs
//   PairRegistration r = registrar.Register(base, base_mask, templ, templ_mask, offset);
//   if (r.ok()) use(r.base_from_template, r.tie_points);
//
// With SCD (include/irmosaic/scd.h) available, PairRegistrar runs SCD first, end to end.
//
// Frames: `base_from_template` maps template pixel coordinates to base pixel coordinates
// (pixel centres at integers, x right, y down). A translation `offset` means template pixel p
// sits at base pixel p + offset.

#include <Eigen/Core>
#include <opencv2/core.hpp>
#include <string>
#include <vector>

#include "irmosaic/export.h"
#include "irmosaic/keypoints.h"
#include "irmosaic/lsm.h"

#if __has_include("irmosaic/scd.h")
#include "irmosaic/scd.h"
#define IRMOSAIC_HAS_SCD 1
#endif

namespace irmosaic {

struct RansacOptions {
  enum class Method { kRansac, kUsacMagsac };
  Method method = Method::kRansac;
  double threshold_px = 1.0;  // Reprojection error (base pixels) for an inlier.
  int max_iterations = 2000;
  double confidence = 0.999;
};

// Options of fine registration, including the accept criteria (docs/matching.md).
struct FineRegistrationOptions {
  LsmOptions lsm;
  KeypointOptions keypoints;
  RansacOptions ransac;
  // Key points keep this many pixels beyond the LSM patch inside both masks, so the patch may
  // move that far during the iterations.
  int margin_px = 3;
  // Pyramid level of the FLSM (single-patch matches and joint fit): 0 at full resolution; 1
  // on half-resolution copies of the overlap (cv::pyrDown) with lsm's filter scales, pixel
  // thresholds and patch divided by 2. The steerable filters are smooth (envelope sigma >=
  // 4.9 px at scale 7: their response to detail finer than 4 px is below 1e-10 of their
  // peak), so the half-resolution image carries what they respond to, in a quarter of the
  // pixels per patch. Key points, positions, sigmas and the homography stay in
  // full-resolution pixels. 0 or 1; FLSM only (docs/matching.md, "In the pipeline").
  int lsm_level = 0;
  // Key points detected on the lsm_level copy (block, pre-blur and spacing scaled to it; the
  // points then sit on level pixels, template pixel = origin + 2 k) instead of at full
  // resolution. No effect at lsm_level 0.
  bool keypoints_at_lsm_level = false;
  // Scale the template to the base's contrast over the overlap before matching (one gain and
  // offset per pair), measured after a Gaussian blur of this sigma.
  bool equalize_gain = true;
  double gain_blur_sigma_px = 3.0;
  // Prior on the homography's distortion for the final refinement on the inliers: standard
  // deviation of its linear terms from identity and of its perspective terms (per px). Tie
  // points in a narrow strip leave some terms unobserved; 0 disables (plain RANSAC + LM).
  double prior_linear_sigma = 0.05;
  double prior_perspective_sigma_per_px = 2e-5;
  // After RANSAC, refine the homography jointly on the FLSM equations of all key-point patches
  // (FLSM only); far steadier under noise than single-patch tie points.
  bool joint_refinement = true;
  int joint_iterations = 10;
  // ... used only when the tie points are too few or their RANSAC fit leaves an inlier RMS
  // above this (px): on clean pairs single-patch tie points are the more precise.
  double joint_above_residual_px = 0.15;
  // Patch centres of the joint fit: a grid of this step (px) over the valid area; 0 uses the
  // key points. Measured at PSNR 20-30 dB: a 16 px grid put slightly more pairs within
  // 0.3 px but accepted more wrong ones, so the key points are the default.
  int joint_grid_step_px = 0;
  // Joint-fit accept criterion: predicted std of the homography at the corners of the key
  // points' box (px).
  double max_joint_sigma_px = 0.25;
  // The same criterion for a joint fit that started from the coarse (SCD) translation alone:
  // too few single-patch tie points for a RANSAC fit, so nothing independent checked the basin
  // it converged in. The stricter of the two limits applies.
  double max_coarse_joint_sigma_px = 0.25;
  // Final direct refinement over the whole overlap (ours): Gauss-Newton on the image difference
  // at every pixel of a Gaussian pyramid level of the overlap (8 homography parameters, gain
  // and offset, the distortion prior above), coarse level first. The key-point patches carry a
  // few hundred filter responses; the overlap holds tens of thousands of pixels, which is what
  // noise at PSNR 20 dB needs (docs/matching.md). Starts from the tie-point (or joint) result.
  bool dense_refinement = true;
  int dense_coarsest_level = 2;  // First stage at 1/2^level of the resolution.
  int dense_finest_level = 1;    // Last stage (0: full resolution).
  int dense_iterations = 10;     // At most, per level.
  // Gaussian smoothing (pixels of the level) of the template before its gradients are taken.
  double dense_gradient_sigma = 1.0;
  // Converged when an update moves every overlap corner by less than this (px).
  double dense_convergence_px = 0.01;
  // Accept criterion of the dense fit: predicted std of the homography at the overlap
  // corners (px). 1/3: the 3-sigma corner error stays under the 1 px a mosaic seam needs.
  double max_dense_sigma_px = 1.0 / 3.0;
  // Accept criteria: a pair is kRejected unless all hold.
  int min_inliers = 10;
  double min_inlier_ratio = 0.5;
  double max_residual_rms_px = 0.8;

  // False with a message when an option is out of range.
  bool IsValid(std::string* error) const;
};

// One correspondence: template pixel <-> base pixel.
struct TiePoint {
  Eigen::Vector2d in_template = Eigen::Vector2d::Zero();
  Eigen::Vector2d in_base = Eigen::Vector2d::Zero();
  double weight = 1.0;  // 1 / (LSM position sigma in px)^2, capped at 1e4.
  bool inlier = false;  // Agrees with the homography within the RANSAC threshold.
};

// Result of registering a pair, with figures a user can print.
struct PairRegistration {
  enum class Status { kOk, kCoarseFailed, kTooFewTiePoints, kRansacFailed, kRejected, kBadInput };
  Status status = Status::kBadInput;
  std::string reason;
  Eigen::Matrix3d base_from_template = Eigen::Matrix3d::Identity();  // Template px -> base px.
  std::vector<TiePoint> tie_points;  // All converged LSM matches, with inlier flags.
  int keypoints = 0;                 // Key points tried.
  // Tie points within the RANSAC threshold of the final homography; when the joint fit ran,
  // the patches agreeing with it (joint_inlier_patches) instead. Under heavy noise few tie
  // points converge: the joint fit can accept a pair whose tie_points hold few inliers.
  int inliers = 0;
  double inlier_ratio = 0.0;     // inliers / tie points (or / joint patches).
  double residual_rms_px = 0.0;  // Of the inliers against the homography, base pixels.
  Eigen::Vector2d offset = Eigen::Vector2d::Zero();  // The coarse translation used.
  // Joint FLSM fit (when enabled): patches used, patches agreeing with the homography,
  // predicted homography std at the key points' box corners (px), and median patch residual
  // over the expected noise residual.
  int joint_patches = 0;
  int joint_inlier_patches = 0;
  double joint_sigma_px = 0.0;
  double joint_residual_ratio = 0.0;
  bool joint_from_coarse = false;  // The joint fit started from the coarse translation alone.
  // Dense fit (when enabled): overlap pixels used at the finest level, predicted homography std
  // at the overlap corners (px), RMS of the final image residual (gray levels), iterations.
  int dense_pixels = 0;
  double dense_sigma_px = 0.0;
  double dense_residual_rms = 0.0;
  int dense_iterations = 0;
#ifdef IRMOSAIC_HAS_SCD
  ScdResult coarse;  // Filled by PairRegistrar.
#endif

  bool ok() const { return status == Status::kOk; }
};

// Name of a status ("ok", "too_few_tie_points", ...).
IRMOSAIC_EXPORT const char* ToString(PairRegistration::Status status);

// Fine registration from a known translation. Holds the LSM filter bank and buffers.
class IRMOSAIC_EXPORT FineRegistrar {
 public:
  // Throws InputError when the options are invalid.
  explicit FineRegistrar(FineRegistrationOptions options = {});

  // Images: one channel, CV_8U, CV_16U or CV_32F, any sizes. Masks: CV_8U (non-zero = data)
  // of the image's size, or empty for all valid. Bad input gives kBadInput, never a throw.
  PairRegistration Register(const cv::Mat& base, const cv::Mat& base_mask, const cv::Mat& templ,
                            const cv::Mat& templ_mask, const Eigen::Vector2d& offset);

  const FineRegistrationOptions& options() const { return options_; }

 private:
  // `box`: bounding box of valid_ (template pixels); (dx, dy): the offset to the base.
  void EqualizeGain(const cv::Rect& box, int dx, int dy);
  // The same on the lsm_level copies (base_l_, templ_l_, valid_l_).
  void EqualizeGainAtLevel(const cv::Rect& box, int dx, int dy);
  struct JointFit {
    int patches = 0, inlier_patches = 0;
    double sigma_px = 1e9, residual_ratio = 1e9;
  };
  // `projected`, when not null, holds ProjectTemplate's result for each of `keypoints`
  // (entries with `projected_ok` false are skipped); null: computed here.
  JointFit JointRefine(const std::vector<Eigen::Vector2d>& keypoints,
                       const std::vector<Eigen::MatrixXd>* projected,
                       const std::vector<bool>* projected_ok, Eigen::Matrix3d* homography);
  struct DenseFit {
    bool ok = false;
    int pixels = 0, iterations = 0;
    double sigma_px = 1e9, residual_rms = 0.0;
  };
  DenseFit DenseRefine(const cv::Mat& base_mask, const cv::Mat& templ_mask,
                       Eigen::Matrix3d* homography);
  bool FitRansac(PairRegistration* out) const;
  void MarkInliers(PairRegistration* out, double* sum_sq) const;

  FineRegistrationOptions options_;
  LsmMatcher lsm_;
  KeypointOptions level_keypoints_;  // options_.keypoints at lsm_level.
  // Float copies of the parts of base and template the pair reads (whole images when the
  // dense fit may run): base_f_ pixel (0, 0) is base pixel base_origin_, and so for the
  // template. valid_ is in whole-template pixels.
  cv::Mat base_f_, templ_f_, valid_, shifted_;
  cv::Point base_origin_, templ_origin_;
  // What base_f_, templ_f_ and valid_ view: buffers that only grow, so pairs of orthoimages of
  // varying size allocate nothing once warm (src/buffer_view.h).
  cv::Mat base_backing_, templ_backing_, valid_backing_;
  // What the FLSM reads: base_f_ and templ_f_ at lsm_level 0, their pyrDown halves at 1 (pixel
  // (0, 0) centred on the float copy's pixel (0, 0); level pixel k is copy pixel 2k).
  cv::Mat base_l_, templ_l_, base_l_backing_, templ_l_backing_;
  // valid_ at the level pixels of templ_l_ (lsm_level > 0).
  cv::Mat valid_l_, valid_l_backing_;
  // Factor on templ_f_'s noise and contrast: the gain equalisation's scale when it was applied
  // to templ_l_ only (1 otherwise).
  double templ_noise_scale_ = 1.0;
  std::vector<cv::Mat> templ_levels_, base_levels_;  // Dense fit pyramids (scratch).
  cv::Mat smoothed_;
  std::vector<float> dense_rows_;  // Dense fit samples (scratch).
  std::vector<float> noise_row_;   // NoiseSigma row buffer (scratch).
  // FLSM template projections of the key points (ProjectTemplate), computed once for the
  // single-patch matches and reused by the joint fit; `projected_ok_` false where the patch
  // does not fit in the template.
  std::vector<Eigen::MatrixXd> projected_;
  std::vector<bool> projected_ok_;
};

#ifdef IRMOSAIC_HAS_SCD
struct PairRegistrationOptions {
  ScdOptions scd;
  FineRegistrationOptions fine;
  bool IsValid(std::string* error) const { return fine.IsValid(error); }
};

// The configuration the Mosaicker registers neighbouring frames with (docs/matching.md,
// "In the pipeline"): the defaults above, with the dense overlap fit off, a joint-fit accept
// bound of 1 px (the optimizer weighs each pair by its accuracy), single-patch LSM
// convergence at 0.02 px (the joint fit, not the single patches, sets a noisy pair's
// homography), the coarse SCD peak without its full-resolution refinement (the LSM
// refines the translation), and the FLSM and the key points on half-resolution copies
// (fine.lsm_level 1, fine.keypoints_at_lsm_level).
IRMOSAIC_EXPORT PairRegistrationOptions PipelineRegistrationOptions();

// SCD coarse translation, then fine registration: the pair registered end to end.
class IRMOSAIC_EXPORT PairRegistrar {
 public:
  explicit PairRegistrar(PairRegistrationOptions options = {});
  // `predicted_offset`: where template pixel (0, 0) is expected in base pixels (from POS);
  // SCD searches within `search_radius_px` of it.
  PairRegistration Register(const cv::Mat& base, const cv::Mat& base_mask, const cv::Mat& templ,
                            const cv::Mat& templ_mask, const Eigen::Vector2d& predicted_offset,
                            double search_radius_px);

 private:
  ScdMatcher scd_;
  FineRegistrar fine_;
};
#endif

// Corner RMSE (px) between two homographies over the corners of a rectangle: the figure the
// tests and benchmarks report.
IRMOSAIC_EXPORT double CornerRmse(const Eigen::Matrix3d& a, const Eigen::Matrix3d& b,
                                  const cv::Rect2d& rect);

}  // namespace irmosaic
