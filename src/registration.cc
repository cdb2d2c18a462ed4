#include "irmosaic/registration.h"

#include <Eigen/Dense>
#include <algorithm>
#include <cmath>
#include <opencv2/calib3d.hpp>
#include <opencv2/imgproc.hpp>
#include <sstream>

#include "irmosaic/error.h"

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

// Gauss-Newton refinement of a homography on the inlier tie points with a Gaussian prior on
// its distortion (linear part near identity, perspective terms near zero), in coordinates
// centred on the tie points' centroid and scaled by 100 px. Tie points in a narrow overlap
// strip leave some of the 8 parameters unobserved; the prior keeps them at the near-translation
// an orthorectified pair has, instead of letting noise extrapolate them.
Eigen::Matrix3d RefineWithPrior(const std::vector<TiePoint>& ties, const Eigen::Matrix3d& start,
                                double point_sigma_px, double linear_sigma,
                                double perspective_sigma_per_px) {
  constexpr double kScale = 100.0;
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
  const double prior_sigma[8] = {linear_sigma,
                                 linear_sigma,
                                 0,
                                 linear_sigma,
                                 linear_sigma,
                                 0,
                                 perspective_sigma_per_px * kScale,
                                 perspective_sigma_per_px * kScale};
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
  if (!(gain_blur_sigma_px > 0.0)) return fail("gain_blur_sigma_px must be > 0");
  if (joint_iterations < 1) return fail("joint_iterations must be >= 1");
  if (joint_grid_step_px < 0) return fail("joint_grid_step_px must be >= 0");
  if (!(max_joint_sigma_px > 0.0)) return fail("max_joint_sigma_px must be > 0");
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

FineRegistrar::FineRegistrar(FineRegistrationOptions options)
    : options_(std::move(options)), lsm_([&] {
        std::string error;
        if (!options_.IsValid(&error)) {
          throw InputError(SourceLocation{"FineRegistrationOptions", 0, 0, ""}, error,
                           "fix the option");
        }
        return options_.lsm;
      }()) {}

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
  base.convertTo(base_f_, CV_32F);
  templ.convertTo(templ_f_, CV_32F);
  if (!cv::checkRange(base_f_) || !cv::checkRange(templ_f_)) {
    out.reason = "an image holds NaN or infinite values";
    return out;
  }

  // Where a key point may sit: its LSM patch (+1 px for gradients, +2 for the cubic kernel,
  // + the margin it may move) inside the template and, shifted by the offset, inside the base.
  const int half = lsm_.patch_radius_px() + 3 + options_.margin_px;
  const cv::Mat base_integral = ValidIntegral(base_mask);
  const cv::Mat templ_integral = ValidIntegral(templ_mask);
  const int dx = static_cast<int>(std::lround(offset.x()));
  const int dy = static_cast<int>(std::lround(offset.y()));
  valid_.create(templ.size(), CV_8U);
  valid_.setTo(0);
  // Only the overlap's bounding box can hold key points.
  const int x_begin = std::max(half, half - dx),
            x_end = std::min(templ.cols - half, base.cols - half - dx);
  const int y_begin = std::max(half, half - dy),
            y_end = std::min(templ.rows - half, base.rows - half - dy);
  for (int y = y_begin; y < y_end; ++y) {
    unsigned char* row = valid_.ptr<unsigned char>(y);
    for (int x = x_begin; x < x_end; ++x) {
      row[x] = SquareValid(templ_integral, templ.size(), x, y, half) &&
                       SquareValid(base_integral, base.size(), x + dx, y + dy, half + 1)
                   ? 255
                   : 0;
    }
  }
  const std::vector<Eigen::Vector2d> keypoints =
      DetectKeypoints(templ_f_, valid_, options_.keypoints);
  if (options_.equalize_gain) EqualizeGain(valid_, dx, dy);
  out.keypoints = static_cast<int>(keypoints.size());

  for (const Eigen::Vector2d& p : keypoints) {
    const LsmResult r = lsm_.Match(base_f_, templ_f_, p, p + offset);
    if (!r.ok()) continue;
    TiePoint tie;
    tie.in_template = p;
    tie.in_base = r.position_in_base;
    tie.weight = std::min(1e4, 1.0 / std::max(1e-8, r.position_sigma_px * r.position_sigma_px));
    out.tie_points.push_back(tie);
  }
  bool joint = options_.joint_refinement && options_.lsm.method == LsmMethod::kFast;
  const int needed = std::max(4, options_.min_inliers);
  bool have_initial = false;
  if (static_cast<int>(out.tie_points.size()) >= needed) {
    have_initial = FitRansac(&out);
  }
  if (have_initial && joint) {
    // Clean pairs: the tie points are more precise than the joint fit; keep them.
    double sum_sq = 0.0;
    MarkInliers(&out, &sum_sq);
    const double rms = std::sqrt(sum_sq / std::max(1, out.inliers));
    joint = out.inliers < needed || rms > options_.joint_above_residual_px;
  }
  if (!have_initial) {
    if (!joint) {
      out.status = static_cast<int>(out.tie_points.size()) < needed
                       ? PairRegistration::Status::kTooFewTiePoints
                       : PairRegistration::Status::kRansacFailed;
      out.reason = out.status == PairRegistration::Status::kRansacFailed
                       ? "RANSAC found no homography"
                       : Figure("converged tie points", out.tie_points.size(), "below", needed) +
                             " (of " + std::to_string(out.keypoints) + " key points)";
      return out;
    }
    // Too few single-patch matches (heavy noise, low texture): the joint solve starts from
    // the coarse translation instead.
    out.base_from_template = Eigen::Matrix3d::Identity();
    out.base_from_template.topRightCorner<2, 1>() = offset;
  }
  if (joint) {
    // The joint fit needs no corners: a dense grid of patches over the valid area carries
    // more of the signal than the capped key points.
    std::vector<Eigen::Vector2d> centres = keypoints;
    if (options_.joint_grid_step_px > 0) {
      centres.clear();
      const cv::Rect box = cv::boundingRect(valid_);
      const int step = options_.joint_grid_step_px;
      for (int y = box.y + (box.height % step) / 2; y < box.br().y; y += step) {
        for (int x = box.x + (box.width % step) / 2; x < box.br().x; x += step) {
          if (valid_.at<unsigned char>(y, x)) centres.emplace_back(x, y);
        }
      }
    }
    const JointFit fit = JointRefine(centres, &out.base_from_template);
    out.joint_patches = fit.patches;
    out.joint_inlier_patches = fit.inlier_patches;
    out.joint_sigma_px = fit.sigma_px;
    out.joint_residual_ratio = fit.residual_ratio;
    if (fit.patches < needed) {
      out.status = PairRegistration::Status::kTooFewTiePoints;
      out.reason = Figure("key-point patches", fit.patches, "below", needed);
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
  if (joint && !(out.joint_sigma_px <= options_.max_joint_sigma_px)) {
    out.reason = Figure("predicted homography sigma", out.joint_sigma_px, "px above",
                        options_.max_joint_sigma_px);
    return out;
  }
  if (out.inliers < options_.min_inliers) {
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

// Immerkaer's noise estimate: the image convolved with a mask that cancels planes and most
// smooth texture; the mean absolute response gives the noise sigma.
static double NoiseSigma(const cv::Mat& image_f) {
  if (image_f.rows < 3 || image_f.cols < 3) return 0.0;
  const cv::Mat kernel = (cv::Mat_<float>(3, 3) << 1, -2, 1, -2, 4, -2, 1, -2, 1);
  cv::Mat response;
  cv::filter2D(image_f, response, CV_32F, kernel);
  const cv::Mat inner = response(cv::Rect(1, 1, image_f.cols - 2, image_f.rows - 2));
  return std::sqrt(M_PI / 2.0) / 6.0 * cv::mean(cv::abs(inner))[0];
}

FineRegistrar::JointFit FineRegistrar::JointRefine(const std::vector<Eigen::Vector2d>& keypoints,
                                                   Eigen::Matrix3d* homography) {
  // All patches share one homography: their 21 filter equations each are stacked into one
  // Gauss-Newton system in its 8 parameters (plus the distortion prior), with Cauchy weights
  // per patch against outliers. Many patches average the noise that defeats single ones.
  constexpr double kScale = 100.0;
  JointFit fit;
  const int r = lsm_.patch_radius_px();
  std::vector<Eigen::Vector2d> points;
  std::vector<Eigen::MatrixXd> designs;
  Eigen::Vector2d centre = Eigen::Vector2d::Zero();
  for (const Eigen::Vector2d& p : keypoints) {
    Eigen::MatrixXd projected;
    if (!lsm_.ProjectTemplate(templ_f_, p, &projected)) continue;
    points.push_back(p);
    designs.push_back(projected);
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
  const double prior_sigma[8] = {options_.prior_linear_sigma,
                                 options_.prior_linear_sigma,
                                 0,
                                 options_.prior_linear_sigma,
                                 options_.prior_linear_sigma,
                                 0,
                                 options_.prior_perspective_sigma_per_px * kScale,
                                 options_.prior_perspective_sigma_per_px * kScale};
  std::vector<Eigen::Matrix<double, Eigen::Dynamic, 8>> rows;
  std::vector<Eigen::VectorXd> rhs;
  std::vector<double> energy;
  // Linearises all patches at x; returns the median patch residual energy.
  auto linearise = [&](const Params& v) {
    rows.clear(), rhs.clear(), energy.clear();
    const Eigen::Matrix3d h = to_homography(v);
    const double eps = 1e-6;
    for (size_t i = 0; i < points.size(); ++i) {
      Eigen::Vector2d c;
      Eigen::Matrix2d m;
      local(h, points[i], &c, &m);
      Eigen::VectorXd responses;
      if (!lsm_.ProjectBase(base_f_, c, m, &responses)) continue;
      const Eigen::Matrix2d m_inv = m.inverse();
      Eigen::Matrix<double, 6, 8> chain;
      for (int k = 0; k < 8; ++k) {
        Params vk = v;
        vk(k) += eps;
        Eigen::Vector2d ck;
        Eigen::Matrix2d mk;
        local(to_homography(vk), points[i], &ck, &mk);
        // Inverse composition: a local increment (d, D) moves c by -M d and M by -M D.
        const Eigen::Vector2d d = -m_inv * (ck - c) / eps;
        const Eigen::Matrix2d big_d = -m_inv * (mk - m) / eps;
        chain.col(k) << d.x(), big_d(0, 0) * r, big_d(0, 1) * r, d.y(), big_d(1, 0) * r,
            big_d(1, 1) * r;
      }
      rows.push_back(designs[i].leftCols(6) * chain);
      rhs.push_back(responses - designs[i].col(6));
      energy.push_back(rhs.back().squaredNorm());
    }
    if (energy.empty()) return 0.0;
    std::vector<double> sorted = energy;
    std::nth_element(sorted.begin(), sorted.begin() + sorted.size() / 2, sorted.end());
    return std::max(1e-12, sorted[sorted.size() / 2]);
  };
  Eigen::Matrix<double, 8, 8> normal;
  auto normal_equations = [&](const Params& v, double median, Params* gradient) {
    const double equation_variance = median / rhs[0].size();
    normal.setZero();
    gradient->setZero();
    for (size_t i = 0; i < rows.size(); ++i) {
      const double w = 1.0 / (1.0 + energy[i] / (9.0 * median)) / equation_variance;
      normal += w * rows[i].transpose() * rows[i];
      *gradient += w * rows[i].transpose() * rhs[i];
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
    if (rows.size() < 4) return fit;
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
    if (motion > 10.0) {  // Runaway: back to the start.
      x = start;
      break;
    }
    x += step;
    if (motion < 0.002) break;
  }
  // Figures at the solution.
  const double median = linearise(x);
  fit.patches = static_cast<int>(rows.size());
  if (fit.patches < 4) return fit;
  Params gradient;
  normal_equations(x, median, &gradient);
  // Expected residual energy of a patch at the right place: noise of both images through 21
  // orthonormal filters.
  // Floor: 2 % of the template's contrast stands for interpolation and model error, so clean
  // images are not judged against a zero noise.
  cv::Scalar mean, contrast;
  cv::meanStdDev(templ_f_, mean, contrast);
  const double floor = 0.02 * contrast[0];
  const double sigma_base = std::max(floor, NoiseSigma(base_f_));
  const double sigma_templ = std::max(floor, NoiseSigma(templ_f_));
  const double expected = rhs[0].size() * (sigma_base * sigma_base + sigma_templ * sigma_templ);
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
  fit.sigma_px = std::sqrt(variance / 4.0);
  *homography = h / h(2, 2);
  return fit;
}

void FineRegistrar::EqualizeGain(const cv::Mat& valid, int dx, int dy) {
  // One gain for the pair, from the overlap's contrast after a blur that removes most sensor
  // noise: steadier than a gain unknown per patch when the noise is heavy.
  const cv::Rect box = cv::boundingRect(valid);
  const cv::Rect in_base = (box + cv::Point(dx, dy)) & cv::Rect(0, 0, base_f_.cols, base_f_.rows);
  if (box.area() < 100 || in_base.size() != box.size()) return;
  cv::Mat a, b;
  cv::GaussianBlur(templ_f_(box), a, cv::Size(), options_.gain_blur_sigma_px);
  cv::GaussianBlur(base_f_(in_base), b, cv::Size(), options_.gain_blur_sigma_px);
  cv::Scalar mean_a, std_a, mean_b, std_b;
  cv::meanStdDev(a, mean_a, std_a, valid(box));
  cv::meanStdDev(b, mean_b, std_b, valid(box));
  if (!(std_a[0] > 1e-6 && std_b[0] > 1e-6)) return;
  templ_f_ = (templ_f_ - mean_a[0]) * (std_b[0] / std_a[0]) + mean_b[0];
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
