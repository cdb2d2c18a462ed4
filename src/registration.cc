#include "irmosaic/registration.h"

#include <Eigen/Dense>
#include <algorithm>
#include <array>
#include <cmath>
#include <opencv2/calib3d.hpp>
#include <opencv2/imgproc.hpp>
#include <sstream>

#include "buffer_view.h"
#include "cubic_weights.h"
#include "irmosaic/error.h"
#include "square_erosion.h"

#if defined(__SSE2__)
#include <emmintrin.h>
#endif

namespace irmosaic {
namespace {

bool UsableImage(const cv::Mat& image) {
  const int depth = image.depth();
  return !image.empty() && image.channels() == 1 &&
         (depth == CV_8U || depth == CV_16U || depth == CV_32F);
}

bool UsableMask(const cv::Mat& mask, const cv::Mat& image) {
  return mask.empty() || (mask.type() == CV_8UC1 && mask.size() == image.size());
}

// Integral image of (mask != 0), or empty for an empty mask (all valid).
cv::Mat ValidIntegral(const cv::Mat& mask) {
  if (mask.empty()) return {};
  cv::Mat binary = mask != 0, integral;
  cv::integral(binary / 255, integral, CV_32S);
  return integral;
}

// True when the square of half-size `half` around (x, y) lies inside the image and, when
// given, entirely inside the mask.
bool SquareValid(const cv::Mat& integral, cv::Size size, int x, int y, int half) {
  if (x - half < 0 || y - half < 0 || x + half >= size.width || y + half >= size.height) {
    return false;
  }
  if (integral.empty()) return true;
  const int x0 = x - half, y0 = y - half, x1 = x + half + 1, y1 = y + half + 1;
  const int sum = integral.at<int>(y1, x1) - integral.at<int>(y0, x1) - integral.at<int>(y1, x0) +
                  integral.at<int>(y0, x0);
  return sum == (2 * half + 1) * (2 * half + 1);
}

std::string Figure(const char* what, double value, const char* relation, double bound) {
  std::ostringstream s;
  s << what << " " << value << " " << relation << " " << bound;
  return s.str();
}

// The homography refinements work in coordinates centred on the overlap and scaled by this many
// pixels, so the 8 parameters have comparable magnitudes.
constexpr double kScale = 100.0;

// Pixels around the valid box that a pair's steps read of the template: the key-point window
// and its filters' reach (blur and corner block, read beyond the window's edge), the LSM
// patches (whose squares the box keeps inside both images) and the gain blur. 40 with the
// default options.
int RegionMargin(const FineRegistrationOptions& o, int patch_radius_px) {
  const KeypointOptions& k = o.keypoints;
  const int keypoints =
      2 * (k.block_size + static_cast<int>(std::ceil(4 * k.presmooth_sigma_px)) + 1);
  const int patches = patch_radius_px + 3;
  const int gain = static_cast<int>(std::ceil(4 * o.gain_blur_sigma_px)) + 1;
  return std::max({keypoints, patches, gain}) + 4;
}

// Prior standard deviations of the 8 homography parameters in those coordinates, in the order
// (h00 - 1, h01, h02, h10, h11 - 1, h12, h20, h21): the linear part near identity, the
// translations free (0: no prior), the perspective terms near zero.
std::array<double, 8> DistortionPriorSigma(double linear_sigma, double perspective_sigma_per_px) {
  const double perspective = perspective_sigma_per_px * kScale;
  return {linear_sigma, linear_sigma, 0, linear_sigma, linear_sigma, 0, perspective, perspective};
}

// Gauss-Newton refinement of a homography on the inlier tie points with a Gaussian prior on
// its distortion (linear part near identity, perspective terms near zero), in coordinates
// centred on the tie points' centroid and scaled by 100 px. Tie points in a narrow overlap
// strip leave some of the 8 parameters unobserved; the prior keeps them at the near-translation
// an orthorectified pair has, instead of letting noise extrapolate them.
Eigen::Matrix3d RefineWithPrior(const std::vector<TiePoint>& ties, const Eigen::Matrix3d& start,
                                double point_sigma_px, double linear_sigma,
                                double perspective_sigma_per_px) {
  Eigen::Vector2d centre = Eigen::Vector2d::Zero();
  int n = 0;
  for (const TiePoint& t : ties) {
    if (t.inlier) centre += t.in_template, ++n;
  }
  if (n < 4) return start;
  centre /= n;
  const Eigen::Vector2d moved = (start * centre.homogeneous()).hnormalized();
  Eigen::Matrix3d from_templ = Eigen::Matrix3d::Identity(), from_base = Eigen::Matrix3d::Identity();
  from_templ.topLeftCorner<2, 2>() /= kScale;
  from_templ.topRightCorner<2, 1>() = -centre / kScale;
  from_base.topLeftCorner<2, 2>() /= kScale;
  from_base.topRightCorner<2, 1>() = -moved / kScale;
  Eigen::Matrix3d h = from_base * start * from_templ.inverse();
  h /= h(2, 2);
  // Parameters: h - I (without h22), 8 of them.
  auto unpack = [](const Eigen::Matrix<double, 8, 1>& x) {
    Eigen::Matrix3d m;
    m << 1 + x(0), x(1), x(2), x(3), 1 + x(4), x(5), x(6), x(7), 1;
    return m;
  };
  Eigen::Matrix<double, 8, 1> x;
  x << h(0, 0) - 1, h(0, 1), h(0, 2), h(1, 0), h(1, 1) - 1, h(1, 2), h(2, 0), h(2, 1);
  const double point_sigma = point_sigma_px / kScale;
  const std::array<double, 8> prior_sigma =
      DistortionPriorSigma(linear_sigma, perspective_sigma_per_px);
  for (int iteration = 0; iteration < 10; ++iteration) {
    Eigen::Matrix<double, 8, 8> normal = Eigen::Matrix<double, 8, 8>::Zero();
    Eigen::Matrix<double, 8, 1> rhs = Eigen::Matrix<double, 8, 1>::Zero();
    const Eigen::Matrix3d m = unpack(x);
    for (const TiePoint& t : ties) {
      if (!t.inlier) continue;
      const Eigen::Vector2d u = (from_templ * t.in_template.homogeneous()).hnormalized();
      const Eigen::Vector2d v = (from_base * t.in_base.homogeneous()).hnormalized();
      const Eigen::Vector3d q = m * u.homogeneous();
      const Eigen::Vector2d e = v - q.hnormalized();
      Eigen::Matrix<double, 2, 8> j;
      const double w = q.z();
      j << u.x() / w, u.y() / w, 1 / w, 0, 0, 0, -u.x() * q.x() / (w * w), -u.y() * q.x() / (w * w),
          0, 0, 0, u.x() / w, u.y() / w, 1 / w, -u.x() * q.y() / (w * w), -u.y() * q.y() / (w * w);
      normal += j.transpose() * j / (point_sigma * point_sigma);
      rhs += j.transpose() * e / (point_sigma * point_sigma);
    }
    for (int k = 0; k < 8; ++k) {
      if (prior_sigma[k] <= 0) continue;
      normal(k, k) += 1.0 / (prior_sigma[k] * prior_sigma[k]);
      rhs(k) -= x(k) / (prior_sigma[k] * prior_sigma[k]);
    }
    const Eigen::Matrix<double, 8, 1> step = normal.ldlt().solve(rhs);
    if (!step.allFinite()) return start;
    x += step;
    if (step.norm() < 1e-10) break;
  }
  Eigen::Matrix3d refined = from_base.inverse() * unpack(x) * from_templ;
  return refined / refined(2, 2);
}

}  // namespace

const char* ToString(PairRegistration::Status status) {
  switch (status) {
    case PairRegistration::Status::kOk:
      return "ok";
    case PairRegistration::Status::kCoarseFailed:
      return "coarse_failed";
    case PairRegistration::Status::kTooFewTiePoints:
      return "too_few_tie_points";
    case PairRegistration::Status::kRansacFailed:
      return "ransac_failed";
    case PairRegistration::Status::kRejected:
      return "rejected";
    case PairRegistration::Status::kBadInput:
      return "bad_input";
  }
  return "unknown";
}

bool FineRegistrationOptions::IsValid(std::string* error) const {
  auto fail = [&](const std::string& m) {
    if (error) *error = m;
    return false;
  };
  if (!lsm.IsValid(error) || !keypoints.IsValid(error)) return false;
  if (!(ransac.threshold_px > 0.0)) return fail("ransac.threshold_px must be > 0");
  if (ransac.max_iterations < 1) return fail("ransac.max_iterations must be >= 1");
  if (!(ransac.confidence > 0.0 && ransac.confidence < 1.0)) {
    return fail("ransac.confidence must be in (0, 1)");
  }
  if (margin_px < 0) return fail("margin_px must be >= 0");
  if (lsm_level < 0 || lsm_level > 1) return fail("lsm_level must be 0 or 1");
  if (lsm_level > 0) {
    if (lsm.method != LsmMethod::kFast) return fail("lsm_level 1 needs the FLSM method");
    for (double s : lsm.scales_px) {
      if (!(s >= 2.0)) return fail("lsm_level 1 needs lsm.scales_px >= 2 px");
    }
  }
  if (!(gain_blur_sigma_px > 0.0)) return fail("gain_blur_sigma_px must be > 0");
  if (joint_iterations < 1) return fail("joint_iterations must be >= 1");
  if (dense_coarsest_level < 0 || dense_coarsest_level > 5 || dense_finest_level < 0 ||
      dense_finest_level > dense_coarsest_level) {
    return fail("dense levels must satisfy 0 <= dense_finest_level <= dense_coarsest_level <= 5");
  }
  if (dense_iterations < 1) return fail("dense_iterations must be >= 1");
  if (!(dense_convergence_px > 0.0)) return fail("dense_convergence_px must be > 0");
  if (!(max_dense_sigma_px > 0.0)) return fail("max_dense_sigma_px must be > 0");
  if (joint_grid_step_px < 0) return fail("joint_grid_step_px must be >= 0");
  if (!(max_joint_sigma_px > 0.0)) return fail("max_joint_sigma_px must be > 0");
  if (!(max_coarse_joint_sigma_px > 0.0)) return fail("max_coarse_joint_sigma_px must be > 0");
  if (!(prior_linear_sigma >= 0.0 && prior_perspective_sigma_per_px > 0.0)) {
    return fail("prior_linear_sigma must be >= 0 and prior_perspective_sigma_per_px > 0");
  }
  if (min_inliers < 4) return fail("min_inliers must be >= 4 (a homography needs 4 points)");
  if (!(min_inlier_ratio >= 0.0 && min_inlier_ratio <= 1.0)) {
    return fail("min_inlier_ratio must be in [0, 1]");
  }
  if (!(max_residual_rms_px > 0.0)) return fail("max_residual_rms_px must be > 0");
  return true;
}

namespace {

// The LSM options at a pyramid level: scales and pixel thresholds in that level's pixels.
LsmOptions LevelLsmOptions(const LsmOptions& o, int level) {
  if (level == 0) return o;
  const double f = std::ldexp(1.0, level);
  LsmOptions l = o;
  for (double& s : l.scales_px) s /= f;
  if (l.tlsm_radius_px > 0) l.tlsm_radius_px = std::max(1, l.tlsm_radius_px >> level);
  l.convergence_px /= f;
  l.max_shift_px /= f;
  l.max_position_sigma_px /= f;
  return l;
}

// The key-point options at a pyramid level: the corner pre-blur less what cv::pyrDown's
// kernel already blurred (variance 1 full-resolution pixel^2 per level), block and spacing in
// that level's pixels.
KeypointOptions LevelKeypointOptions(const KeypointOptions& o, int level) {
  if (level == 0) return o;
  const double f = std::ldexp(1.0, level);
  const double pyramid_variance = (f * f - 1.0) / 3.0;  // 1 at level 1, 5 at level 2.
  KeypointOptions l = o;
  l.presmooth_sigma_px =
      std::sqrt(std::max(0.0, o.presmooth_sigma_px * o.presmooth_sigma_px - pyramid_variance)) / f;
  l.block_size = std::max(3, (static_cast<int>(o.block_size / f)) | 1);
  l.min_distance_px = o.min_distance_px / f;
  return l;
}

// `r` grown by `by` on every side and clipped to `bounds`, its origin moved only by even
// amounts: the region keeps the parity of r's corner, so a pyrDown of it samples the image at
// the same points wherever the image sits in a larger canvas.
cv::Rect GrowKeepingParity(const cv::Rect& r, int by, const cv::Rect& bounds) {
  by += by & 1;
  cv::Rect g(r.x - by, r.y - by, r.width + 2 * by, r.height + 2 * by);
  if (g.x < bounds.x) {
    const int shift = (bounds.x - g.x + 1) & ~1;
    g.x += shift;
    g.width -= shift;
  }
  if (g.y < bounds.y) {
    const int shift = (bounds.y - g.y + 1) & ~1;
    g.y += shift;
    g.height -= shift;
  }
  return g & bounds;
}

}  // namespace

FineRegistrar::FineRegistrar(FineRegistrationOptions options)
    : options_(std::move(options)),
      lsm_([&] {
        std::string error;
        if (!options_.IsValid(&error)) {
          throw InputError(SourceLocation{"FineRegistrationOptions", 0, 0, ""}, error,
                           "fix the option");
        }
        return LevelLsmOptions(options_.lsm, options_.lsm_level);
      }()),
      level_keypoints_(LevelKeypointOptions(options_.keypoints, options_.lsm_level)) {}

PairRegistration FineRegistrar::Register(const cv::Mat& base, const cv::Mat& base_mask,
                                         const cv::Mat& templ, const cv::Mat& templ_mask,
                                         const Eigen::Vector2d& offset) {
  PairRegistration out;
  out.offset = offset;
  if (!UsableImage(base) || !UsableImage(templ)) {
    out.reason = "images must be non-empty, one channel, 8-bit, 16-bit or float";
    return out;
  }
  if (!UsableMask(base_mask, base) || !UsableMask(templ_mask, templ)) {
    out.reason = "masks must be empty or CV_8U of their image's size";
    return out;
  }
  if (!offset.allFinite() || offset.cwiseAbs().maxCoeff() > 1e6) {
    out.reason = "the coarse offset is not finite";
    return out;
  }
  // Only float input can hold NaN or infinities; the 8- and 16-bit POS orthoimages need no
  // pass over their whole area for it.
  if ((base.depth() == CV_32F && !cv::checkRange(base)) ||
      (templ.depth() == CV_32F && !cv::checkRange(templ))) {
    out.reason = "an image holds NaN or infinite values";
    return out;
  }

  // Where a key point may sit: its LSM patch (+1 px for gradients, +2 for the cubic kernel,
  // + the margin it may move) inside the template and, shifted by the offset, inside the base
  // (one pixel more there).
  // At lsm_level 1 the key points keep the same distance from the masks' edges as at level 0
  // (the filters span the same ground): a level-1 patch's outermost ring of level pixels and
  // pyrDown's kernel then read up to 3 px further, where the filters are below 2 % of their
  // peak and an orthoimage's border replicates the frame's. Measured on 600 pipeline pairs
  // (bench/pipeline_pairs_bench), keeping the 3 px more clear of the edges instead cost
  // accuracy on narrow strip overlaps (median corner error 0.359 -> 0.402 px): the points
  // nearest the strip's edges hold its rotation.
  const int level = options_.lsm_level;
  const double level_scale = std::ldexp(1.0, level);
  const int patch_reach = (level == 0 ? lsm_.patch_radius_px() : 2 * lsm_.patch_radius_px()) + 3;
  const int half = patch_reach + options_.margin_px;
  const int dx = static_cast<int>(std::lround(offset.x()));
  const int dy = static_cast<int>(std::lround(offset.y()));
  valid_ = BufferView(&valid_backing_, templ.size(), CV_8U);
  valid_.setTo(0);
  // Only the overlap's bounding box can hold key points: the template pixels whose square
  // lies inside the template and whose shifted square lies inside the base.
  const int x_begin = std::max(half, half + 1 - dx),
            x_end = std::min(templ.cols - half, base.cols - half - 1 - dx);
  const int y_begin = std::max(half, half + 1 - dy),
            y_end = std::min(templ.rows - half, base.rows - half - 1 - dy);
  cv::Rect valid_box;  // Bounding box of the valid pixels.
  if (x_end > x_begin && y_end > y_begin) {
    const cv::Rect region(x_begin, y_begin, x_end - x_begin, y_end - y_begin);
    const cv::Mat in_templ = SquaresInsideMask(templ_mask, region, half);
    const cv::Mat in_base = SquaresInsideMask(base_mask, region + cv::Point(dx, dy), half + 1);
    cv::Mat valid_region = valid_(region);
    cv::bitwise_and(in_templ, in_base, valid_region);
    valid_box = cv::boundingRect(valid_region) + region.tl();
  }
  // The float copies: around the valid box only, unless the dense fit (which reads the whole
  // overlap) may run. Everything the pair reads of the template lies within RegionMargin of
  // the box (key-point patches, the corner response's and the gain blur's reach); of the base,
  // within that plus a key point's square, which bounds where a converging patch can go
  // (LsmOptions::max_shift_px). The noise and contrast figures of the joint fit are those of
  // these regions: the overlap, not the whole orthoimages.
  cv::Rect templ_region(0, 0, templ.cols, templ.rows), base_region(0, 0, base.cols, base.rows);
  if (!options_.dense_refinement && !valid_box.empty()) {
    const int margin = RegionMargin(options_, patch_reach - 3);
    const int reach = margin + static_cast<int>(std::ceil(options_.lsm.max_shift_px));
    auto grow = [](const cv::Rect& r, int by) {
      return cv::Rect(r.x - by, r.y - by, r.width + 2 * by, r.height + 2 * by);
    };
    if (level == 0) {
      templ_region &= grow(valid_box, margin);
      base_region &= grow(valid_box + cv::Point(dx, dy), half + 1 + reach);
    } else {
      templ_region = GrowKeepingParity(valid_box, margin, templ_region);
      base_region = GrowKeepingParity(valid_box + cv::Point(dx, dy), half + 1 + reach, base_region);
    }
  }
  templ_origin_ = templ_region.tl();
  base_origin_ = base_region.tl();
  const Eigen::Vector2d templ_origin(templ_origin_.x, templ_origin_.y);
  const Eigen::Vector2d base_origin(base_origin_.x, base_origin_.y);
  base_f_ = BufferView(&base_backing_, base_region.size(), CV_32F);
  templ_f_ = BufferView(&templ_backing_, templ_region.size(), CV_32F);
  base(base_region).convertTo(base_f_, CV_32F);
  templ(templ_region).convertTo(templ_f_, CV_32F);
  // Homographies between whole-image pixels and the float copies' pixels.
  Eigen::Matrix3d templ_to_local = Eigen::Matrix3d::Identity();
  Eigen::Matrix3d local_to_base = Eigen::Matrix3d::Identity();
  templ_to_local.topRightCorner<2, 1>() = -templ_origin;
  local_to_base.topRightCorner<2, 1>() = base_origin;
  // ... and the FLSM level's pixels (the same at level 0).
  Eigen::Matrix3d level_from_local = Eigen::Matrix3d::Identity();
  level_from_local.topLeftCorner<2, 2>() /= level_scale;

  // The key points and the gain see the valid box only (plus the margin the corner response
  // reads beyond it, as DetectKeypoints computes it in src/keypoints.cc: keep the two equal, or
  // points near the window's edge would change): no scans of the whole orthoimage for the box.
  // Key points at full resolution unless keypoints_at_lsm_level asks for them on the level
  // copy (below).
  std::vector<Eigen::Vector2d> keypoints;
  const bool level_keypoints = level > 0 && options_.keypoints_at_lsm_level;
  if (!valid_box.empty() && !level_keypoints) {
    const KeypointOptions& k = options_.keypoints;
    const int reach = k.block_size + static_cast<int>(3 * k.presmooth_sigma_px) + 1;
    const cv::Rect window = (valid_box + cv::Size(2 * reach, 2 * reach) - cv::Point(reach, reach)) &
                            cv::Rect(0, 0, templ.cols, templ.rows);
    keypoints = DetectKeypoints(templ_f_(window - templ_origin_), valid_(window), k);
    for (Eigen::Vector2d& p : keypoints) p += Eigen::Vector2d(window.x, window.y);
  }
  templ_noise_scale_ = 1.0;
  if (level == 0) {
    if (options_.equalize_gain) EqualizeGain(valid_box, dx, dy);
    base_l_ = base_f_;
    templ_l_ = templ_f_;
  } else {
    // The gain at the level needs the two copies' level pixels to meet the same template and
    // base pixels under the offset: always when the copies keep the valid box's parity (dense
    // fit off), else only for an even offset; otherwise it is estimated at full resolution.
    const bool level_gain = (templ_origin_.x + dx - base_origin_.x) % 2 == 0 &&
                            (templ_origin_.y + dy - base_origin_.y) % 2 == 0;
    if (options_.equalize_gain && !level_gain) EqualizeGain(valid_box, dx, dy);
    auto half_size = [](const cv::Mat& m) { return cv::Size((m.cols + 1) / 2, (m.rows + 1) / 2); };
    base_l_ = BufferView(&base_l_backing_, half_size(base_f_), CV_32F);
    templ_l_ = BufferView(&templ_l_backing_, half_size(templ_f_), CV_32F);
    cv::pyrDown(base_f_, base_l_, base_l_.size());
    cv::pyrDown(templ_f_, templ_l_, templ_l_.size());
    if ((options_.equalize_gain && level_gain) || level_keypoints) {
      // The valid pixels that are level pixels (copy pixel 2k).
      valid_l_ = BufferView(&valid_l_backing_, templ_l_.size(), CV_8U);
      for (int y = 0; y < valid_l_.rows; ++y) {
        const unsigned char* src =
            valid_.ptr<unsigned char>(templ_origin_.y + 2 * y) + templ_origin_.x;
        unsigned char* dst = valid_l_.ptr<unsigned char>(y);
        for (int x = 0; x < valid_l_.cols; ++x) dst[x] = src[2 * x];
      }
    }
    if (options_.equalize_gain && level_gain) EqualizeGainAtLevel(valid_box, dx, dy);
    if (level_keypoints && !valid_box.empty()) {
      // Level pixel k is template pixel templ_origin + 2 k: the LSM's template patches then
      // sit on level pixels, without interpolation.
      keypoints = DetectKeypoints(templ_l_, valid_l_, level_keypoints_);
      for (Eigen::Vector2d& p : keypoints) p = templ_origin + level_scale * p;
    }
  }
  out.keypoints = static_cast<int>(keypoints.size());

  // FLSM: the template projections of the key points serve the single-patch matches and the
  // joint fit alike (the template does not change in between), so they are computed once.
  const bool fast = options_.lsm.method == LsmMethod::kFast;
  projected_.resize(keypoints.size());
  projected_ok_.assign(keypoints.size(), false);
  for (size_t i = 0; i < keypoints.size(); ++i) {
    const Eigen::Vector2d& p = keypoints[i];
    LsmResult r;
    if (fast) {
      projected_ok_[i] =
          lsm_.ProjectTemplate(templ_l_, (p - templ_origin) / level_scale, &projected_[i]);
      if (!projected_ok_[i]) continue;  // Match: out of bounds.
      r = lsm_.MatchProjected(base_l_, projected_[i], (p + offset - base_origin) / level_scale);
    } else {
      r = lsm_.Match(base_f_, templ_f_, p - templ_origin, p + offset - base_origin);
    }
    if (!r.ok()) continue;
    TiePoint tie;
    tie.in_template = p;
    tie.in_base = r.position_in_base * level_scale + base_origin;
    const double sigma = r.position_sigma_px * level_scale;
    tie.weight = std::min(1e4, 1.0 / std::max(1e-8, sigma * sigma));
    out.tie_points.push_back(tie);
  }
  // The dense fit supersedes the joint FLSM fit (both serve noisy pairs; the dense one uses
  // every overlap pixel).
  bool joint = options_.joint_refinement && !options_.dense_refinement &&
               options_.lsm.method == LsmMethod::kFast;
  const int needed = std::max(4, options_.min_inliers);
  bool have_initial = false;
  if (static_cast<int>(out.tie_points.size()) >= needed) {
    have_initial = FitRansac(&out);
  }
  bool run_dense = options_.dense_refinement;
  if (have_initial && (joint || run_dense)) {
    // Clean pairs: the tie points are more precise than the joint or dense fit; keep them.
    double sum_sq = 0.0;
    MarkInliers(&out, &sum_sq);
    const double rms = std::sqrt(sum_sq / std::max(1, out.inliers));
    const bool noisy = out.inliers < needed || rms > options_.joint_above_residual_px;
    joint = joint && noisy;
    run_dense = run_dense && noisy;
  }
  if (!have_initial) {
    if (!joint && !options_.dense_refinement) {
      out.status = static_cast<int>(out.tie_points.size()) < needed
                       ? PairRegistration::Status::kTooFewTiePoints
                       : PairRegistration::Status::kRansacFailed;
      out.reason = out.status == PairRegistration::Status::kRansacFailed
                       ? "RANSAC found no homography"
                       : Figure("converged tie points", out.tie_points.size(), "below", needed) +
                             " (of " + std::to_string(out.keypoints) + " key points)";
      return out;
    }
    // Too few single-patch matches (heavy noise, low texture): the joint or dense solve starts
    // from the coarse translation instead.
    out.base_from_template = Eigen::Matrix3d::Identity();
    out.base_from_template.topRightCorner<2, 1>() = offset;
  }
  if (joint) {
    // The joint fit needs no corners: a dense grid of patches over the valid area carries
    // more of the signal than the capped key points.
    std::vector<Eigen::Vector2d> centres = keypoints;
    const bool reuse = options_.joint_grid_step_px <= 0;
    if (!reuse) {
      centres.clear();
      const cv::Rect box = cv::boundingRect(valid_);
      const int step = options_.joint_grid_step_px;
      for (int y = box.y + (box.height % step) / 2; y < box.br().y; y += step) {
        for (int x = box.x + (box.width % step) / 2; x < box.br().x; x += step) {
          if (valid_.at<unsigned char>(y, x)) centres.emplace_back(x, y);
        }
      }
    }
    for (Eigen::Vector2d& c : centres) c = (c - templ_origin) / level_scale;
    // In the FLSM level's pixels of the two float copies.
    Eigen::Matrix3d local = level_from_local * local_to_base.inverse() * out.base_from_template *
                            templ_to_local.inverse() * level_from_local.inverse();
    const JointFit fit = JointRefine(centres, reuse ? &projected_ : nullptr,
                                     reuse ? &projected_ok_ : nullptr, &local);
    out.base_from_template =
        local_to_base * level_from_local.inverse() * local * level_from_local * templ_to_local;
    out.base_from_template /= out.base_from_template(2, 2);
    out.joint_patches = fit.patches;
    out.joint_inlier_patches = fit.inlier_patches;
    out.joint_sigma_px = fit.sigma_px;
    out.joint_residual_ratio = fit.residual_ratio;
    out.joint_from_coarse = !have_initial;
    if (fit.patches < needed) {
      out.status = PairRegistration::Status::kTooFewTiePoints;
      out.reason = Figure("key-point patches", fit.patches, "below", needed);
      return out;
    }
  }
  bool dense = false;
  if (run_dense) {
    Eigen::Matrix3d h = out.base_from_template;
    const DenseFit fit = DenseRefine(base_mask, templ_mask, &h);
    out.dense_pixels = fit.pixels;
    out.dense_iterations = fit.iterations;
    out.dense_sigma_px = fit.sigma_px;
    out.dense_residual_rms = fit.residual_rms;
    if (fit.ok && (have_initial || fit.sigma_px <= options_.max_dense_sigma_px)) {
      out.base_from_template = h;
      dense = true;
    } else if (!have_initial && !joint) {
      out.status = static_cast<int>(out.tie_points.size()) < needed
                       ? PairRegistration::Status::kTooFewTiePoints
                       : PairRegistration::Status::kRansacFailed;
      out.reason = (out.status == PairRegistration::Status::kRansacFailed
                        ? std::string("RANSAC found no homography")
                        : Figure("converged tie points", out.tie_points.size(), "below", needed) +
                              " (of " + std::to_string(out.keypoints) + " key points)") +
                   (fit.ok ? Figure("; dense fit sigma", fit.sigma_px, "px above",
                                    options_.max_dense_sigma_px)
                           : std::string("; the dense fit failed"));
      return out;
    }
  }
  double sum_sq = 0.0;
  MarkInliers(&out, &sum_sq);
  out.residual_rms_px = out.inliers > 0 ? std::sqrt(sum_sq / out.inliers) : 0.0;
  out.inlier_ratio =
      out.tie_points.empty() ? 0.0 : static_cast<double>(out.inliers) / out.tie_points.size();
  if (joint) {
    // Quality from the joint fit: patches agreeing with the homography.
    out.inliers = out.joint_inlier_patches;
    out.inlier_ratio = static_cast<double>(out.joint_inlier_patches) / out.joint_patches;
  }

  out.status = PairRegistration::Status::kRejected;
  if (dense && !(out.dense_sigma_px <= options_.max_dense_sigma_px)) {
    out.reason = Figure("predicted homography sigma (dense fit)", out.dense_sigma_px, "px above",
                        options_.max_dense_sigma_px);
    return out;
  }
  if (!dense && joint && !(out.joint_sigma_px <= options_.max_joint_sigma_px)) {
    out.reason = Figure("predicted homography sigma", out.joint_sigma_px, "px above",
                        options_.max_joint_sigma_px);
    return out;
  }
  if (!dense && joint && out.joint_from_coarse &&
      !(out.joint_sigma_px <= options_.max_coarse_joint_sigma_px)) {
    out.reason = Figure("predicted homography sigma of a fit from the coarse translation alone",
                        out.joint_sigma_px, "px above", options_.max_coarse_joint_sigma_px);
    return out;
  }
  if (dense && out.inliers < options_.min_inliers) {
    // Under heavy noise few patches converge; the dense fit's own figures decide, with the
    // tie points (when there are enough) as a check against a wrong basin.
    if (static_cast<int>(out.tie_points.size()) >= options_.min_inliers &&
        out.inlier_ratio < options_.min_inlier_ratio) {
      out.reason = Figure("inlier ratio", out.inlier_ratio, "below", options_.min_inlier_ratio);
    } else {
      out.status = PairRegistration::Status::kOk;
    }
  } else if (out.inliers < options_.min_inliers) {
    out.reason = Figure("inliers", out.inliers, "below", options_.min_inliers);
  } else if (out.inlier_ratio < options_.min_inlier_ratio) {
    out.reason = Figure("inlier ratio", out.inlier_ratio, "below", options_.min_inlier_ratio);
  } else if (out.residual_rms_px > options_.max_residual_rms_px) {
    out.reason = Figure("inlier residual RMS", out.residual_rms_px, "px above",
                        options_.max_residual_rms_px);
  } else {
    out.status = PairRegistration::Status::kOk;
  }
  return out;
}

bool FineRegistrar::FitRansac(PairRegistration* out) const {
  std::vector<cv::Point2d> from, to;
  for (const TiePoint& t : out->tie_points) {
    from.emplace_back(t.in_template.x(), t.in_template.y());
    to.emplace_back(t.in_base.x(), t.in_base.y());
  }
  const int method =
      options_.ransac.method == RansacOptions::Method::kRansac ? cv::RANSAC : cv::USAC_MAGSAC;
  cv::Mat inlier_mask;
  const cv::Mat h = cv::findHomography(from, to, method, options_.ransac.threshold_px, inlier_mask,
                                       options_.ransac.max_iterations, options_.ransac.confidence);
  if (h.empty() || !cv::checkRange(h)) return false;
  for (int r = 0; r < 3; ++r) {
    for (int c = 0; c < 3; ++c) out->base_from_template(r, c) = h.at<double>(r, c);
  }
  out->base_from_template /= out->base_from_template(2, 2);
  if (options_.prior_linear_sigma > 0.0) {
    double sum_sq = 0.0;
    MarkInliers(out, &sum_sq);
    const double rms = std::sqrt(sum_sq / std::max(1, out->inliers));
    out->base_from_template =
        RefineWithPrior(out->tie_points, out->base_from_template, std::max(0.05, rms),
                        options_.prior_linear_sigma, options_.prior_perspective_sigma_per_px);
  }
  return true;
}

void FineRegistrar::MarkInliers(PairRegistration* out, double* sum_sq) const {
  out->inliers = 0;
  *sum_sq = 0.0;
  for (TiePoint& t : out->tie_points) {
    const Eigen::Vector3d q = out->base_from_template * t.in_template.homogeneous();
    const double e = (q.hnormalized() - t.in_base).norm();
    t.inlier = e <= options_.ransac.threshold_px;
    if (t.inlier) {
      ++out->inliers;
      *sum_sq += e * e;
    }
  }
}

// Standard deviation of a CV_32F image's pixels (what cv::meanStdDev gives, to rounding):
// sums of the values less the first pixel's, in float lanes per row and doubles across rows,
// so the shift keeps the squares small for images far from zero (16-bit thermal) and the lanes
// let the compiler vectorise; cv::meanStdDev took 3-5 % of a pair's CPU.
static double StandardDeviation(const cv::Mat& image_f) {
  const int rows = image_f.rows, cols = image_f.cols;
  if (rows < 1 || cols < 1) return 0.0;
  const float ref = image_f.at<float>(0, 0);
  constexpr int kLanes = 8;
  double sum = 0.0, sum_sq = 0.0;
  for (int y = 0; y < rows; ++y) {
    const float* p = image_f.ptr<float>(y);
    float s[kLanes] = {}, q[kLanes] = {};
    int x = 0;
#if defined(__SSE2__)
    // The lanes in registers (as in NoiseSigma below): the same operations per lane, in the
    // same order.
    {
      const __m128 r = _mm_set1_ps(ref);
      __m128 s0 = _mm_setzero_ps(), s1 = _mm_setzero_ps(), q0 = _mm_setzero_ps(),
             q1 = _mm_setzero_ps();
      for (; x + kLanes <= cols; x += kLanes) {
        const __m128 v0 = _mm_sub_ps(_mm_loadu_ps(p + x), r);
        const __m128 v1 = _mm_sub_ps(_mm_loadu_ps(p + x + 4), r);
        s0 = _mm_add_ps(s0, v0);
        s1 = _mm_add_ps(s1, v1);
        q0 = _mm_add_ps(q0, _mm_mul_ps(v0, v0));
        q1 = _mm_add_ps(q1, _mm_mul_ps(v1, v1));
      }
      _mm_storeu_ps(s, s0);
      _mm_storeu_ps(s + 4, s1);
      _mm_storeu_ps(q, q0);
      _mm_storeu_ps(q + 4, q1);
    }
#endif
    for (; x + kLanes <= cols; x += kLanes) {
      for (int k = 0; k < kLanes; ++k) {
        const float v = p[x + k] - ref;
        s[k] += v;
        q[k] += v * v;
      }
    }
    double row_s = 0.0, row_q = 0.0;
    for (; x < cols; ++x) {
      const double v = static_cast<double>(p[x]) - ref;
      row_s += v;
      row_q += v * v;
    }
    for (int k = 0; k < kLanes; ++k) row_s += s[k], row_q += q[k];
    sum += row_s;
    sum_sq += row_q;
  }
  const double n = static_cast<double>(rows) * cols, mean = sum / n;
  return std::sqrt(std::max(0.0, sum_sq / n - mean * mean));
}

// Immerkaer's noise estimate: the image convolved with a mask that cancels planes and most
// smooth texture; the mean absolute response gives the noise sigma. The mask is separable
// ([1 -2 1] down, then across), so one pass with a row buffer does it: no response image the
// size of the orthoimage, no second pass for its absolute value and mean.
static double NoiseSigma(const cv::Mat& image_f, std::vector<float>* row_buffer) {
  const int rows = image_f.rows, cols = image_f.cols;
  if (rows < 3 || cols < 3) return 0.0;
  row_buffer->resize(static_cast<size_t>(cols));
  float* down_second = row_buffer->data();  // Vertical second difference of the current row.
  // Independent partial sums the compiler can keep in vector lanes (a single float
  // accumulator would be a serial chain); each lane sums at most cols / 8 values.
  constexpr int kLanes = 8;
  double total = 0.0;
  for (int y = 1; y + 1 < rows; ++y) {
    const float* up = image_f.ptr<float>(y - 1);
    const float* mid = image_f.ptr<float>(y);
    const float* down = image_f.ptr<float>(y + 1);
    int x = 0;
#if defined(__SSE2__)
    // The compiler's -O2 cost model leaves this loop scalar; the vector lanes do the same
    // operations in the same order.
    const __m128 two = _mm_set1_ps(2.0f);
    for (; x + 4 <= cols; x += 4) {
      const __m128 second =
          _mm_add_ps(_mm_sub_ps(_mm_loadu_ps(up + x), _mm_mul_ps(two, _mm_loadu_ps(mid + x))),
                     _mm_loadu_ps(down + x));
      _mm_storeu_ps(down_second + x, second);
    }
#endif
    for (; x < cols; ++x) down_second[x] = up[x] - 2.0f * mid[x] + down[x];
    float lanes[kLanes] = {};
    x = 1;
#if defined(__SSE2__)
    // The lanes in registers: the compiler's vector loop kept them in memory, a store and a
    // reload per 4 pixels (half of the function's time). The same operations per lane, in the
    // same order, so the same sums.
    {
      const __m128 sign = _mm_set1_ps(-0.0f);
      __m128 low = _mm_setzero_ps(), high = _mm_setzero_ps();
      for (; x + kLanes < cols; x += kLanes) {
        const float* d = down_second + x;
        low = _mm_add_ps(
            low, _mm_andnot_ps(sign, _mm_add_ps(_mm_sub_ps(_mm_loadu_ps(d - 1),
                                                           _mm_mul_ps(two, _mm_loadu_ps(d))),
                                                _mm_loadu_ps(d + 1))));
        high = _mm_add_ps(
            high, _mm_andnot_ps(sign, _mm_add_ps(_mm_sub_ps(_mm_loadu_ps(d + 3),
                                                            _mm_mul_ps(two, _mm_loadu_ps(d + 4))),
                                                 _mm_loadu_ps(d + 5))));
      }
      _mm_storeu_ps(lanes, low);
      _mm_storeu_ps(lanes + 4, high);
    }
#endif
    for (; x + kLanes < cols; x += kLanes) {
      for (int k = 0; k < kLanes; ++k) {
        lanes[k] +=
            std::abs(down_second[x + k - 1] - 2.0f * down_second[x + k] + down_second[x + k + 1]);
      }
    }
    double row = 0.0;
    for (; x + 1 < cols; ++x) {
      row += std::abs(down_second[x - 1] - 2.0f * down_second[x] + down_second[x + 1]);
    }
    for (int k = 0; k < kLanes; ++k) row += lanes[k];
    total += row;
  }
  const double mean_abs = total / (static_cast<double>(rows - 2) * (cols - 2));
  return std::sqrt(M_PI / 2.0) / 6.0 * mean_abs;
}

FineRegistrar::JointFit FineRegistrar::JointRefine(const std::vector<Eigen::Vector2d>& keypoints,
                                                   const std::vector<Eigen::MatrixXd>* projected,
                                                   const std::vector<bool>* projected_ok,
                                                   Eigen::Matrix3d* homography) {
  // All patches share one homography: their 21 filter equations each are stacked into one
  // Gauss-Newton system in its 8 parameters (plus the distortion prior), with Cauchy weights
  // per patch against outliers. Many patches average the noise that defeats single ones.
  JointFit fit;
  const int r = lsm_.patch_radius_px();
  std::vector<Eigen::Vector2d> points;
  // The patches' template projections: the caller's, or computed here into `own`.
  std::vector<const Eigen::MatrixXd*> designs;
  std::vector<Eigen::MatrixXd> own;
  if (projected == nullptr) own.resize(keypoints.size());
  Eigen::Vector2d centre = Eigen::Vector2d::Zero();
  for (size_t i = 0; i < keypoints.size(); ++i) {
    const Eigen::Vector2d& p = keypoints[i];
    if (projected != nullptr) {
      if (!(*projected_ok)[i]) continue;
      designs.push_back(&(*projected)[i]);
    } else {
      if (!lsm_.ProjectTemplate(templ_l_, p, &own[i])) continue;
      designs.push_back(&own[i]);
    }
    points.push_back(p);
    centre += p;
  }
  if (points.size() < 4) return fit;
  centre /= static_cast<double>(points.size());
  const Eigen::Vector2d moved = (*homography * centre.homogeneous()).hnormalized();
  Eigen::Matrix3d from_templ = Eigen::Matrix3d::Identity(), from_base = Eigen::Matrix3d::Identity();
  from_templ.topLeftCorner<2, 2>() /= kScale;
  from_templ.topRightCorner<2, 1>() = -centre / kScale;
  from_base.topLeftCorner<2, 2>() /= kScale;
  from_base.topRightCorner<2, 1>() = -moved / kScale;
  const Eigen::Matrix3d to_base = from_base.inverse();
  Eigen::Matrix3d hn = from_base * *homography * from_templ.inverse();
  hn /= hn(2, 2);
  using Params = Eigen::Matrix<double, 8, 1>;
  Params x;
  x << hn(0, 0) - 1, hn(0, 1), hn(0, 2), hn(1, 0), hn(1, 1) - 1, hn(1, 2), hn(2, 0), hn(2, 1);
  auto to_homography = [&](const Params& v) {
    Eigen::Matrix3d m;
    m << 1 + v(0), v(1), v(2), v(3), 1 + v(4), v(5), v(6), v(7), 1;
    return Eigen::Matrix3d(to_base * m * from_templ);
  };
  // Position and local linear map of a homography at p (central differences, 1 px).
  auto local = [](const Eigen::Matrix3d& h, const Eigen::Vector2d& p, Eigen::Vector2d* c,
                  Eigen::Matrix2d* m) {
    auto at = [&](double dx, double dy) {
      return Eigen::Vector2d((h * Eigen::Vector3d(p.x() + dx, p.y() + dy, 1)).hnormalized());
    };
    *c = at(0, 0);
    m->col(0) = 0.5 * (at(1, 0) - at(-1, 0));
    m->col(1) = 0.5 * (at(0, 1) - at(0, -1));
  };
  // Everything here is in the FLSM level's pixels (FineRegistrationOptions::lsm_level): a
  // level pixel is `f` full-resolution pixels.
  const double f = std::ldexp(1.0, options_.lsm_level);
  const std::array<double, 8> prior_sigma = DistortionPriorSigma(
      options_.prior_linear_sigma, options_.prior_perspective_sigma_per_px * f);
  // Each linearised patch's rows (its filter equations in the 8 parameters) and right-hand
  // side, stacked: patch k's are rows [k n, (k + 1) n) of `rows` and `rhs`.
  const int n = static_cast<int>(designs.empty() ? 0 : designs[0]->rows());
  Eigen::Matrix<double, Eigen::Dynamic, 8> rows(static_cast<Eigen::Index>(points.size()) * n, 8);
  Eigen::VectorXd rhs(rows.rows());
  std::vector<double> energy, sorted;
  energy.reserve(points.size());
  Eigen::VectorXd responses;
  // Linearises all patches at x; returns the median patch residual energy.
  auto linearise = [&](const Params& v) {
    energy.clear();
    const Eigen::Matrix3d h = to_homography(v);
    const double eps = 1e-6;
    std::array<Eigen::Matrix3d, 8> perturbed;
    for (int k = 0; k < 8; ++k) {
      Params vk = v;
      vk(k) += eps;
      perturbed[k] = to_homography(vk);
    }
    for (size_t i = 0; i < points.size(); ++i) {
      Eigen::Vector2d c;
      Eigen::Matrix2d m;
      local(h, points[i], &c, &m);
      if (!lsm_.ProjectBase(base_l_, c, m, &responses)) continue;
      const Eigen::Matrix2d m_inv = m.inverse();
      Eigen::Matrix<double, 6, 8> chain;
      for (int k = 0; k < 8; ++k) {
        Eigen::Vector2d ck;
        Eigen::Matrix2d mk;
        local(perturbed[k], points[i], &ck, &mk);
        // Inverse composition: a local increment (d, D) moves c by -M d and M by -M D.
        const Eigen::Vector2d d = -m_inv * (ck - c) / eps;
        const Eigen::Matrix2d big_d = -m_inv * (mk - m) / eps;
        chain.col(k) << d.x(), big_d(0, 0) * r, big_d(0, 1) * r, d.y(), big_d(1, 0) * r,
            big_d(1, 1) * r;
      }
      const Eigen::Index at = static_cast<Eigen::Index>(energy.size()) * n;
      rows.middleRows(at, n).noalias() = designs[i]->leftCols(6) * chain;
      rhs.segment(at, n) = responses - designs[i]->col(6);
      energy.push_back(rhs.segment(at, n).squaredNorm());
    }
    if (energy.empty()) return 0.0;
    sorted = energy;
    std::nth_element(sorted.begin(), sorted.begin() + sorted.size() / 2, sorted.end());
    return std::max(1e-12, sorted[sorted.size() / 2]);
  };
  Eigen::Matrix<double, 8, 8> normal;
  auto normal_equations = [&](const Params& v, double median, Params* gradient) {
    const double equation_variance = median / n;
    normal.setZero();
    gradient->setZero();
    for (size_t i = 0; i < energy.size(); ++i) {
      const double w = 1.0 / (1.0 + energy[i] / (9.0 * median)) / equation_variance;
      const auto block = rows.middleRows(static_cast<Eigen::Index>(i) * n, n);
      normal += w * block.transpose() * block;
      *gradient += w * block.transpose() * rhs.segment(static_cast<Eigen::Index>(i) * n, n);
    }
    for (int k = 0; k < 8; ++k) {
      if (prior_sigma[k] <= 0) continue;
      normal(k, k) += 1.0 / (prior_sigma[k] * prior_sigma[k]);
      (*gradient)(k) -= v(k) / (prior_sigma[k] * prior_sigma[k]);
    }
  };
  const Params start = x;
  for (int iteration = 0; iteration < options_.joint_iterations; ++iteration) {
    const double median = linearise(x);
    if (energy.size() < 4) return fit;
    Params gradient;
    normal_equations(x, median, &gradient);
    const Params step = normal.ldlt().solve(gradient);
    if (!step.allFinite()) break;
    const Eigen::Matrix3d before = to_homography(x), after = to_homography(x + step);
    double motion = 0.0;
    for (const Eigen::Vector2d& p : points) {
      motion = std::max(motion, ((after * p.homogeneous()).hnormalized() -
                                 (before * p.homogeneous()).hnormalized())
                                    .norm());
    }
    if (motion > 10.0 / f) {  // Runaway: back to the start.
      x = start;
      break;
    }
    x += step;
    if (motion < 0.002 / f) break;
  }
  // Figures at the solution.
  const double median = linearise(x);
  fit.patches = static_cast<int>(energy.size());
  if (fit.patches < 4) return fit;
  Params gradient;
  normal_equations(x, median, &gradient);
  // Expected residual energy of a patch at the right place: noise of both images through 21
  // orthonormal filters.
  // Floor: 2 % of the template's contrast stands for interpolation and model error, so clean
  // images are not judged against a zero noise.
  // Both from the full-resolution copies: at level 1 the orthonormal filters' responses, to
  // the texture and to white noise alike, are half those at full resolution (a level pixel
  // averages 4), while pyrDown's correlated noise would mislead Immerkaer's estimate.
  // templ_noise_scale_: the gain equalisation when it scaled only the level copy.
  const double floor = 0.02 * StandardDeviation(templ_f_) * templ_noise_scale_ / f;
  const double sigma_base = std::max(floor, NoiseSigma(base_f_, &noise_row_) / f);
  const double sigma_templ =
      std::max(floor, NoiseSigma(templ_f_, &noise_row_) * templ_noise_scale_ / f);
  const double expected = n * (sigma_base * sigma_base + sigma_templ * sigma_templ);
  const double scale = std::max(median, expected);
  for (double e : energy) fit.inlier_patches += e <= 4.0 * scale;
  fit.residual_ratio = median / std::max(expected, 1e-6);
  const Eigen::Matrix<double, 8, 8> covariance = normal.inverse();
  double variance = 0.0;
  const double eps = 1e-6;
  const Eigen::Matrix3d h = to_homography(x);
  double x0 = 1e9, y0 = 1e9, x1 = -1e9, y1 = -1e9;
  for (const Eigen::Vector2d& p : points) {
    x0 = std::min(x0, p.x()), y0 = std::min(y0, p.y());
    x1 = std::max(x1, p.x()), y1 = std::max(y1, p.y());
  }
  for (const Eigen::Vector2d& corner : {Eigen::Vector2d(x0, y0), Eigen::Vector2d(x1, y0),
                                        Eigen::Vector2d(x1, y1), Eigen::Vector2d(x0, y1)}) {
    Eigen::Matrix<double, 2, 8> j;
    const Eigen::Vector2d q = (h * corner.homogeneous()).hnormalized();
    for (int k = 0; k < 8; ++k) {
      Params vk = x;
      vk(k) += eps;
      j.col(k) = ((to_homography(vk) * corner.homogeneous()).hnormalized() - q) / eps;
    }
    variance += (j * covariance * j.transpose()).trace() / 2.0;
  }
  fit.sigma_px = std::sqrt(variance / 4.0) * f;
  *homography = h / h(2, 2);
  return fit;
}

namespace {

// Bicubic sample of a CV_32F image; the caller keeps (x, y) in [1, size - 3).
inline float SampleCubic(const cv::Mat& image, double x, double y) {
  const int x0 = static_cast<int>(x), y0 = static_cast<int>(y);
  float wx[4], wy[4];
  CubicWeights(static_cast<float>(x - x0), wx);
  CubicWeights(static_cast<float>(y - y0), wy);
  const size_t step = image.step1();
  const float* p = image.ptr<float>(y0 - 1) + x0 - 1;
  float sum = 0.0f;
  for (int j = 0; j < 4; ++j, p += step) {
    sum += wy[j] * (wx[0] * p[0] + wx[1] * p[1] + wx[2] * p[2] + wx[3] * p[3]);
  }
  return sum;
}

// The covariance above treats the level's samples as independent; cv::pyrDown's kernel
// correlates the noise of neighbouring samples. For a signal smoother than the sample spacing
// the variance of a least-squares estimate grows by the sum of the noise autocorrelation over
// all lags (relative to lag 0), per axis. Returns the factor on a standard deviation.
double PyramidNoiseFactor(int level) {
  std::vector<double> h = {1.0};
  for (int l = 0; l < level; ++l) {
    // Kernel of one more pyrDown, in full-resolution taps: [1 4 6 4 1] / 16 at stride 2^l.
    const int stride = 1 << l;
    std::vector<double> next(h.size() + 4 * stride, 0.0);
    const double k[5] = {1 / 16.0, 4 / 16.0, 6 / 16.0, 4 / 16.0, 1 / 16.0};
    for (size_t i = 0; i < h.size(); ++i) {
      for (int t = 0; t < 5; ++t) next[i + t * stride] += h[i] * k[t];
    }
    h = next;
  }
  const int stride = 1 << level;
  double r0 = 0.0, total = 0.0;
  for (int m = -static_cast<int>(h.size()); m <= static_cast<int>(h.size()); ++m) {
    double r = 0.0;
    for (int i = 0; i < static_cast<int>(h.size()); ++i) {
      const int j = i + m * stride;
      if (j >= 0 && j < static_cast<int>(h.size())) r += h[i] * h[j];
    }
    if (m == 0) r0 = r;
    total += r;
  }
  return total / r0;  // Per axis on the variance = both axes on the standard deviation.
}

// Bounding box of the template pixels that the homography maps into the base image.
cv::Rect2d OverlapBox(const Eigen::Matrix3d& base_from_template, cv::Size base, cv::Size templ) {
  const Eigen::Matrix3d inv = base_from_template.inverse();
  double x0 = 1e18, y0 = 1e18, x1 = -1e18, y1 = -1e18;
  for (const Eigen::Vector2d& c :
       {Eigen::Vector2d(0, 0), Eigen::Vector2d(base.width - 1, 0),
        Eigen::Vector2d(base.width - 1, base.height - 1), Eigen::Vector2d(0, base.height - 1)}) {
    const Eigen::Vector3d q = inv * c.homogeneous();
    if (!(q.z() > 0)) return {};
    x0 = std::min(x0, q.x() / q.z()), y0 = std::min(y0, q.y() / q.z());
    x1 = std::max(x1, q.x() / q.z()), y1 = std::max(y1, q.y() / q.z());
  }
  x0 = std::max(x0, 0.0), y0 = std::max(y0, 0.0);
  x1 = std::min(x1, templ.width - 1.0), y1 = std::min(y1, templ.height - 1.0);
  if (!(x1 > x0 && y1 > y0)) return {};
  return {x0, y0, x1 - x0, y1 - y0};
}

}  // namespace

FineRegistrar::DenseFit FineRegistrar::DenseRefine(const cv::Mat& base_mask,
                                                   const cv::Mat& templ_mask,
                                                   Eigen::Matrix3d* homography) {
  // Inverse-compositional Gauss-Newton over every overlap pixel of a pyramid level: the
  // template's gradients (and so the normal matrix) are computed once per level; each
  // iteration resamples the base (bicubic) at the homography's image of the samples.
  // Unknowns: 8 homography parameters in coordinates centred on the overlap and scaled by
  // 100 px (as the distortion prior), a gain and an offset.
  DenseFit fit;
  Eigen::Matrix3d h = *homography;
  const cv::Rect2d box = OverlapBox(h, base_f_.size(), templ_f_.size());
  if (box.width < 16 || box.height < 16) return fit;
  const int top = options_.dense_coarsest_level;
  const int bottom = std::min(top, options_.dense_finest_level);
  const int reach = (2 << top) + 4;  // Pyramid kernel and gradient support, full-res px.
  const cv::Rect templ_roi =
      cv::Rect(static_cast<int>(box.x) - reach, static_cast<int>(box.y) - reach,
               static_cast<int>(box.width) + 2 * reach + 1,
               static_cast<int>(box.height) + 2 * reach + 1) &
      cv::Rect(0, 0, templ_f_.cols, templ_f_.rows);
  double bx0 = 1e18, by0 = 1e18, bx1 = -1e18, by1 = -1e18;
  for (const Eigen::Vector2d& c :
       {Eigen::Vector2d(templ_roi.x, templ_roi.y), Eigen::Vector2d(templ_roi.br().x, templ_roi.y),
        Eigen::Vector2d(templ_roi.br().x, templ_roi.br().y),
        Eigen::Vector2d(templ_roi.x, templ_roi.br().y)}) {
    const Eigen::Vector2d q = (h * c.homogeneous()).hnormalized();
    bx0 = std::min(bx0, q.x()), by0 = std::min(by0, q.y());
    bx1 = std::max(bx1, q.x()), by1 = std::max(by1, q.y());
  }
  if (!(std::isfinite(bx0) && std::isfinite(bx1) && std::isfinite(by0) && std::isfinite(by1))) {
    return fit;
  }
  const cv::Rect base_roi =
      cv::Rect(static_cast<int>(std::floor(bx0)) - reach, static_cast<int>(std::floor(by0)) - reach,
               static_cast<int>(bx1 - bx0) + 2 * reach + 2,
               static_cast<int>(by1 - by0) + 2 * reach + 2) &
      cv::Rect(0, 0, base_f_.cols, base_f_.rows);
  if (templ_roi.width < 16 || templ_roi.height < 16 || base_roi.width < 16 ||
      base_roi.height < 16) {
    return fit;
  }
  templ_levels_.resize(top + 1);
  base_levels_.resize(top + 1);
  templ_levels_[0] = templ_f_(templ_roi);
  base_levels_[0] = base_f_(base_roi);
  for (int level = 1; level <= top; ++level) {
    cv::pyrDown(templ_levels_[level - 1], templ_levels_[level]);
    cv::pyrDown(base_levels_[level - 1], base_levels_[level]);
  }
  const cv::Mat templ_integral = ValidIntegral(templ_mask);
  const cv::Mat base_integral = ValidIntegral(base_mask);
  const Eigen::Vector2d centre(box.x + 0.5 * box.width, box.y + 0.5 * box.height);
  Eigen::Matrix3d from_templ = Eigen::Matrix3d::Identity();
  from_templ.topLeftCorner<2, 2>() /= kScale;
  from_templ.topRightCorner<2, 1>() = -centre / kScale;
  const Eigen::Matrix3d to_templ = from_templ.inverse();
  const Eigen::Vector2d corners[4] = {{box.x, box.y},
                                      {box.x + box.width, box.y},
                                      {box.x + box.width, box.y + box.height},
                                      {box.x, box.y + box.height}};
  const std::array<double, 8> prior_sigma =
      DistortionPriorSigma(options_.prior_linear_sigma, options_.prior_perspective_sigma_per_px);
  using Vector10 = Eigen::Matrix<double, 10, 1>;
  using Matrix10 = Eigen::Matrix<double, 10, 10>;
  constexpr int kStride = 11;  // Per sample: x, y (full-res template px), T, 8 geometric terms.
  double gain = 1.0, offset = 0.0;
  Matrix10 normal = Matrix10::Identity();
  for (int level = top; level >= bottom; --level) {
    const cv::Mat& t = templ_levels_[level];
    const cv::Mat& b = base_levels_[level];
    const double unit = static_cast<double>(1 << level);
    const int support = (1 << (level + 1)) + 1;  // Mask check half-size, full-res px.
    // Samples: level pixels inside the overlap box, valid in both masks over their support.
    dense_rows_.clear();
    Matrix10 h0 = Matrix10::Zero();
    const double grad_scale = 0.5 * kScale / unit;  // Central difference -> per 100 px.
    // Gradients of a smoothed template: noisy gradients inflate the normal matrix (slow,
    // shrunken steps and an optimistic covariance) without adding information.
    if (options_.dense_gradient_sigma > 0) {
      cv::GaussianBlur(t, smoothed_, cv::Size(), options_.dense_gradient_sigma);
    } else {
      smoothed_ = t;
    }
    for (int j = 2; j < t.rows - 2; ++j) {
      const float* row = t.ptr<float>(j);
      const float* up = smoothed_.ptr<float>(j - 1);
      const float* down = smoothed_.ptr<float>(j + 1);
      const float* mid = smoothed_.ptr<float>(j);
      const double y = templ_roi.y + unit * j;
      if (y < box.y || y > box.y + box.height) continue;
      for (int i = 2; i < t.cols - 2; ++i) {
        const double x = templ_roi.x + unit * i;
        if (x < box.x || x > box.x + box.width) continue;
        const int xi = static_cast<int>(std::lround(x)), yi = static_cast<int>(std::lround(y));
        if (!templ_integral.empty() &&
            !SquareValid(templ_integral, templ_f_.size(), xi, yi, support)) {
          continue;
        }
        const Eigen::Vector2d q = (h * Eigen::Vector3d(x, y, 1)).hnormalized();
        const double qx = (q.x() - base_roi.x) / unit, qy = (q.y() - base_roi.y) / unit;
        if (!(qx >= 3 && qy >= 3 && qx < b.cols - 5 && qy < b.rows - 5)) continue;
        if (!base_integral.empty() &&
            !SquareValid(base_integral, base_f_.size(), static_cast<int>(std::lround(q.x())),
                         static_cast<int>(std::lround(q.y())), support)) {
          continue;
        }
        const double u = (x - centre.x()) / kScale, v = (y - centre.y()) / kScale;
        const double gx = grad_scale * (mid[i + 1] - mid[i - 1]);
        const double gy = grad_scale * (down[i] - up[i]);
        const double radial = gx * u + gy * v;
        Vector10 jrow;
        jrow << gx * u, gx * v, gx, gy * u, gy * v, gy, -radial * u, -radial * v, row[i], 1.0;
        h0.selfadjointView<Eigen::Lower>().rankUpdate(jrow);
        dense_rows_.push_back(static_cast<float>(x));
        dense_rows_.push_back(static_cast<float>(y));
        dense_rows_.push_back(row[i]);
        for (int k = 0; k < 8; ++k) dense_rows_.push_back(static_cast<float>(jrow(k)));
      }
    }
    h0 = h0.selfadjointView<Eigen::Lower>();
    const int samples = static_cast<int>(dense_rows_.size()) / kStride;
    if (samples < 200) return fit;
    fit.pixels = samples;
    for (int iteration = 0; iteration < options_.dense_iterations; ++iteration) {
      ++fit.iterations;
      Eigen::Matrix<double, 8, 1> g_geo = Eigen::Matrix<double, 8, 1>::Zero();
      double g_t = 0, g_1 = 0, sse = 0;
      int used = 0;
      const double h00 = h(0, 0), h01 = h(0, 1), h02 = h(0, 2), h10 = h(1, 0), h11 = h(1, 1),
                   h12 = h(1, 2), h20 = h(2, 0), h21 = h(2, 1), h22 = h(2, 2);
      const double inv_unit = 1.0 / unit;
      float g[8] = {0, 0, 0, 0, 0, 0, 0, 0};
      for (int s = 0; s < samples; ++s) {
        const float* r = &dense_rows_[static_cast<size_t>(s) * kStride];
        const double w = 1.0 / (h20 * r[0] + h21 * r[1] + h22);
        const double qx = ((h00 * r[0] + h01 * r[1] + h02) * w - base_roi.x) * inv_unit;
        const double qy = ((h10 * r[0] + h11 * r[1] + h12) * w - base_roi.y) * inv_unit;
        if (!(qx >= 1 && qy >= 1 && qx < b.cols - 3 && qy < b.rows - 3)) continue;
        const float e = SampleCubic(b, qx, qy) - static_cast<float>(gain * r[2] + offset);
        for (int k = 0; k < 8; ++k) g[k] += r[3 + k] * e;
        g_t += r[2] * e;
        g_1 += e;
        sse += static_cast<double>(e) * e;
        ++used;
      }
      if (used < samples * 0.9) return fit;  // The homography moved the overlap away.
      for (int k = 0; k < 8; ++k) g_geo(k) = g[k];
      const double variance = std::max(sse / used, 1e-6);
      fit.residual_rms = std::sqrt(sse / used);
      Eigen::Matrix<double, 10, 1> scale;
      scale << gain, gain, gain, gain, gain, gain, gain, gain, 1, 1;
      normal = scale.asDiagonal() * h0 * scale.asDiagonal() / variance;
      Vector10 rhs;
      rhs << gain * g_geo, g_t, g_1;
      rhs /= variance;
      // Prior on the total distortion; an increment d changes it by about -d (inverse
      // composition near the identity).
      Eigen::Matrix3d hn = h * to_templ;
      const Eigen::Vector2d moved = (h * centre.homogeneous()).hnormalized();
      Eigen::Matrix3d from_base = Eigen::Matrix3d::Identity();
      from_base.topLeftCorner<2, 2>() /= kScale;
      from_base.topRightCorner<2, 1>() = -moved / kScale;
      hn = from_base * hn;
      hn /= hn(2, 2);
      const double total[8] = {hn(0, 0) - 1, hn(0, 1), hn(0, 2), hn(1, 0),
                               hn(1, 1) - 1, hn(1, 2), hn(2, 0), hn(2, 1)};
      for (int k = 0; k < 8; ++k) {
        if (prior_sigma[k] <= 0) continue;
        const double p = 1.0 / (prior_sigma[k] * prior_sigma[k]);
        normal(k, k) += p;
        rhs(k) += p * total[k];
      }
      const Vector10 delta = normal.ldlt().solve(rhs);
      if (!delta.allFinite()) return fit;
      Eigen::Matrix3d w;
      w << 1 + delta(0), delta(1), delta(2), delta(3), 1 + delta(4), delta(5), delta(6), delta(7),
          1;
      Eigen::Matrix3d next = h * to_templ * w.inverse() * from_templ;
      next /= next(2, 2);
      gain += delta(8);
      offset += delta(9);
      double motion = 0.0;
      for (const Eigen::Vector2d& c : corners) {
        motion = std::max(
            motion,
            ((next * c.homogeneous()).hnormalized() - (h * c.homogeneous()).hnormalized()).norm());
      }
      if (!next.allFinite() || motion > 20.0 || !(gain > 0.2 && gain < 5.0)) return fit;
      h = next;
      if (motion < options_.dense_convergence_px) break;
    }
  }
  // Predicted std at the overlap corners from the covariance of the last linearisation.
  const Eigen::Matrix<double, 8, 8> covariance = normal.inverse().topLeftCorner<8, 8>();
  double variance = 0.0;
  for (const Eigen::Vector2d& c : corners) {
    const double u = (c.x() - centre.x()) / kScale, v = (c.y() - centre.y()) / kScale;
    Eigen::Matrix<double, 2, 8> j;
    j << u, v, 1, 0, 0, 0, -u * u, -u * v, 0, 0, 0, u, v, 1, -u * v, -v * v;
    j *= kScale;
    variance += (j * covariance * j.transpose()).trace();
  }
  fit.sigma_px = std::sqrt(variance / 4.0) * PyramidNoiseFactor(bottom);
  fit.ok = true;
  *homography = h;
  return fit;
}

void FineRegistrar::EqualizeGain(const cv::Rect& box, int dx, int dy) {
  // One gain for the pair, from the overlap's contrast after a blur that removes most sensor
  // noise: steadier than a gain unknown per patch when the noise is heavy.
  const cv::Mat& valid = valid_;
  const cv::Rect in_base =
      (box + cv::Point(dx, dy)) & (cv::Rect(0, 0, base_f_.cols, base_f_.rows) + base_origin_);
  if (box.area() < 100 || in_base.size() != box.size()) return;
  cv::Mat a, b;
  cv::GaussianBlur(templ_f_(box - templ_origin_), a, cv::Size(), options_.gain_blur_sigma_px);
  cv::GaussianBlur(base_f_(in_base - base_origin_), b, cv::Size(), options_.gain_blur_sigma_px);
  cv::Scalar mean_a, std_a, mean_b, std_b;
  cv::meanStdDev(a, mean_a, std_a, valid(box));
  cv::meanStdDev(b, mean_b, std_b, valid(box));
  if (!(std_a[0] > 1e-6 && std_b[0] > 1e-6)) return;
  templ_f_ = (templ_f_ - mean_a[0]) * (std_b[0] / std_a[0]) + mean_b[0];
}

void FineRegistrar::EqualizeGainAtLevel(const cv::Rect& box, int dx, int dy) {
  // As EqualizeGain, on the half-resolution copies: pyrDown has blurred by 1 full-resolution
  // pixel already, the rest of the blur is applied in level pixels. The gain goes into the
  // level copy the LSM reads; the full-resolution template (read afterwards only for its noise
  // and contrast, and by the dense fit) is scaled too when the dense fit may run, else its
  // figures are scaled instead.
  const int f = 1 << options_.lsm_level;
  const cv::Rect in_base =
      (box + cv::Point(dx, dy)) & (cv::Rect(0, 0, base_f_.cols, base_f_.rows) + base_origin_);
  if (box.area() < 100 || in_base.size() != box.size()) return;
  auto level_rect = [f](const cv::Rect& r, cv::Point origin) {
    const cv::Point tl((r.x - origin.x) / f, (r.y - origin.y) / f);
    return cv::Rect(
        tl, cv::Point((r.br().x - origin.x + f - 1) / f, (r.br().y - origin.y + f - 1) / f));
  };
  const cv::Rect t = level_rect(box, templ_origin_) & cv::Rect(0, 0, templ_l_.cols, templ_l_.rows);
  const cv::Rect b = level_rect(in_base, base_origin_) & cv::Rect(0, 0, base_l_.cols, base_l_.rows);
  if (t.size() != b.size() || t.area() < 4) return;
  const double sigma = options_.gain_blur_sigma_px;
  const double pyramid_variance = (f * f - 1.0) / 3.0;
  const double level_sigma = std::sqrt(std::max(0.25, sigma * sigma - pyramid_variance)) / f;
  cv::Mat a, c;
  cv::GaussianBlur(templ_l_(t), a, cv::Size(), level_sigma);
  cv::GaussianBlur(base_l_(b), c, cv::Size(), level_sigma);
  cv::Scalar mean_a, std_a, mean_c, std_c;
  cv::meanStdDev(a, mean_a, std_a, valid_l_(t));
  cv::meanStdDev(c, mean_c, std_c, valid_l_(t));
  if (!(std_a[0] > 1e-6 && std_c[0] > 1e-6)) return;
  const double scale = std_c[0] / std_a[0], shift = mean_c[0] - mean_a[0] * scale;
  templ_l_.convertTo(templ_l_, CV_32F, scale, shift);
  if (options_.dense_refinement) {
    templ_f_.convertTo(templ_f_, CV_32F, scale, shift);
  } else {
    templ_noise_scale_ = scale;
  }
}

double CornerRmse(const Eigen::Matrix3d& a, const Eigen::Matrix3d& b, const cv::Rect2d& rect) {
  double sum_sq = 0.0;
  const Eigen::Vector2d corners[4] = {{rect.x, rect.y},
                                      {rect.x + rect.width, rect.y},
                                      {rect.x + rect.width, rect.y + rect.height},
                                      {rect.x, rect.y + rect.height}};
  for (const Eigen::Vector2d& c : corners) {
    const Eigen::Vector2d pa = (a * c.homogeneous()).hnormalized();
    const Eigen::Vector2d pb = (b * c.homogeneous()).hnormalized();
    sum_sq += (pa - pb).squaredNorm();
  }
  return std::sqrt(sum_sq / 4.0);
}

#ifdef IRMOSAIC_HAS_SCD
PairRegistrationOptions PipelineRegistrationOptions() {
  PairRegistrationOptions o;
  // A pair known to 1 px is still worth far more to the optimizer than POS (metres); the
  // registration's own stricter default is for single pairs.
  o.fine.max_joint_sigma_px = 1.0;
  // Unless the joint fit started from SCD's translation alone (too few single-patch tie points
  // for RANSAC): then nothing checked its basin, and when the true offset lay outside the search
  // radius it converged next to a wrong peak. On 8836 accepted pairs of five 900-frame
  // stretches of the hour's flight (`pipeline_pairs_bench --first N`), the 50 accepted that way
  // split at this limit: above it 6, five of them 29-103 px wrong (their true offsets 80-97 px
  // from the prediction, beyond the 64 px radius) and one right to 1.1 px; below it 44 at
  // 0.11-0.75 px, 37 within 1 px, 5 within 3.1 px, 2 off by 8.6 and 9.6 px (docs/matching.md,
  // "In the pipeline").
  o.fine.max_coarse_joint_sigma_px = 0.8;
  // Off: on the bundled sample it raised the mean placement error from 2.02 to 3.08 px
  // (scripts/run-sample.sh), through its known bias on unblurred noisy pairs ("Dense
  // refinement" in docs/matching.md).
  o.fine.dense_refinement = false;
  // Noisy pairs take their homography from the joint fit, which starts from the single-patch
  // tie points' RANSAC fit: stopping those at 0.01 px instead of 0.005 px moved the pair
  // homographies of 120 sample-flight pairs by at most 0.0001 px, for fewer LSM iterations;
  // 0.02 px moved those of 200 pairs by at most 0.00002 px, for 6 % less CPU per pair (0.05:
  // no faster) (docs/benchmarks.md, "Session 23").
  o.fine.lsm.convergence_px = 0.02;
  // The coarse SCD peak (quarter resolution) seeds the LSM, which refines the translation
  // anyway: against the simulator's truth on 200 pairs of the sample flight, registered from
  // the coarse peak the homographies were as accurate over the overlap (median corner error
  // 0.332 px against 0.335, 90th percentile 0.79 against 0.82) and one pair that the refined
  // peak sent 21 px astray registered to 0.47 px; the full-resolution refinement was about a
  // quarter of the pair's CPU (docs/benchmarks.md, "Session 14").
  o.scd.refine_at_full_resolution = false;
  // The FLSM on half-resolution copies of the overlap: against the truth on 600 pairs of the
  // sample flight, median / 90th percentile corner error 0.359 / 0.904 px against 0.347 /
  // 0.888 at full resolution, for 16.7 -> 11.9 CPU ms per pair; over 1000 frames the
  // foreground's CPU per frame -22 %, frames/s +16 %, the final placements' mean +0.9 %
  // (docs/benchmarks.md, "Session 15").
  o.fine.lsm_level = 1;
  // Key points on that half-resolution copy too: 1 CPU ms less per pair; over 750-frame
  // flights of 8 seeds the placements the same (mean 1.116 against 1.118 px, paired
  // difference -0.003 +- 0.019 px), pipeline CPU per frame -7 % (docs/benchmarks.md,
  // "Session 24"). One seed alone (the sample's, 7) had looked worse, 1.07 -> 1.12 px.
  o.fine.keypoints_at_lsm_level = true;
  return o;
}

PairRegistrar::PairRegistrar(PairRegistrationOptions options)
    : scd_(options.scd), fine_(options.fine) {}

PairRegistration PairRegistrar::Register(const cv::Mat& base, const cv::Mat& base_mask,
                                         const cv::Mat& templ, const cv::Mat& templ_mask,
                                         const Eigen::Vector2d& predicted_offset,
                                         double search_radius_px) {
  const ScdResult coarse =
      scd_.Match(base, base_mask, templ, templ_mask, predicted_offset, search_radius_px);
  if (!coarse.ok()) {
    PairRegistration out;
    out.status = coarse.status == ScdResult::Status::kBadInput
                     ? PairRegistration::Status::kBadInput
                     : PairRegistration::Status::kCoarseFailed;
    out.reason = "coarse matching (SCD): " + coarse.reason;
    out.offset = predicted_offset;
    out.coarse = coarse;
    return out;
  }
  PairRegistration out = fine_.Register(base, base_mask, templ, templ_mask, coarse.offset);
  out.coarse = coarse;
  return out;
}
#endif

}  // namespace irmosaic
