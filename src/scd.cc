// Masked SCD template matching in the frequency domain (PAPER_NOTES.md, "SCD").
#include "irmosaic/scd.h"

#include <algorithm>
#include <cmath>
#include <limits>
#include <opencv2/imgproc.hpp>
#include <sstream>
#include <vector>

namespace irmosaic {
namespace {

using Status = ScdResult::Status;

bool IsSupportedImage(const cv::Mat& image) {
  const int depth = image.depth();
  return image.dims == 2 && image.channels() == 1 &&
         (depth == CV_8U || depth == CV_16U || depth == CV_32F);
}

// Empty, or CV_8U one channel of the image's size.
bool IsSupportedMask(const cv::Mat& mask, const cv::Mat& image) {
  return mask.empty() || (mask.type() == CV_8UC1 && mask.size() == image.size());
}

// 1D full convolution of two small kernels.
std::vector<double> Convolve(const std::vector<double>& a, const std::vector<double>& b) {
  std::vector<double> out(a.size() + b.size() - 1, 0.0);
  for (size_t i = 0; i < a.size(); ++i) {
    for (size_t j = 0; j < b.size(); ++j) out[i + j] += a[i] * b[j];
  }
  return out;
}

double SumOfSquares(const std::vector<double>& v) {
  double s = 0.0;
  for (double x : v) s += x * x;
  return s;
}

// Immerkaer (1996) noise std of a float image: sqrt(pi/2)/6 * mean |I * N| over `valid`
// (N the difference of two Laplacians, blind to planes and linear ramps).
double EstimateNoiseStd(const cv::Mat& image_f32, const cv::Mat& valid_u8, cv::Mat* scratch) {
  static const cv::Mat kKernel = (cv::Mat_<float>(3, 3) << 1, -2, 1, -2, 4, -2, 1, -2, 1);
  cv::filter2D(image_f32, *scratch, CV_32F, kKernel, cv::Point(-1, -1), 0, cv::BORDER_REFLECT);
  const double mean_abs = valid_u8.empty() ? cv::norm(*scratch, cv::NORM_L1) / scratch->total()
                                           : cv::mean(cv::abs(*scratch), valid_u8)[0];
  return std::sqrt(CV_PI / 2.0) / 6.0 * mean_abs;
}

// Sub-pixel position of a peak from its two neighbours (c the peak value); in [-0.5, 0.5].
double ParabolaDelta(double left, double centre, double right) {
  const double curvature = left - 2.0 * centre + right;
  if (!(curvature < 0.0)) return 0.0;
  return std::clamp(0.5 * (left - right) / curvature, -0.5, 0.5);
}

double RefineAxis(ScdSubpixel mode, double left, double centre, double right) {
  if (mode == ScdSubpixel::kGaussian && left > 0 && centre > 0 && right > 0) {
    return ParabolaDelta(std::log(left), std::log(centre), std::log(right));
  }
  return ParabolaDelta(left, centre, right);
}

std::string Describe(const cv::Mat& m) {
  std::ostringstream s;
  s << m.cols << "x" << m.rows << " type " << m.type() << " channels " << m.channels();
  return s.str();
}

}  // namespace

const char* ToString(ScdResult::Status status) {
  switch (status) {
    case Status::kOk:
      return "ok";
    case Status::kTooLittleOverlap:
      return "too little overlap";
    case Status::kAmbiguous:
      return "ambiguous";
    case Status::kFlat:
      return "flat";
    case Status::kBadInput:
      return "bad input";
  }
  return "unknown";
}

bool ScdOptions::IsValid(std::string* error) const {
  auto fail = [error](const std::string& why) {
    if (error) *error = why;
    return false;
  };
  if (!(gradient_sigma_px >= 0.0 && gradient_sigma_px <= 20.0)) {
    return fail("gradient_sigma_px must be in [0, 20]");
  }
  if (!(min_overlap_fraction >= 0.0 && min_overlap_fraction <= 1.0)) {
    return fail("min_overlap_fraction must be in [0, 1]");
  }
  if (!(noise_floor_sigmas >= 0.0 && noise_floor_sigmas <= 100.0)) {
    return fail("noise_floor_sigmas must be in [0, 100]");
  }
  if (!(min_oriented_fraction >= 0.0 && min_oriented_fraction <= 1.0)) {
    return fail("min_oriented_fraction must be in [0, 1]");
  }
  if (!(min_peak_ratio >= 1.0 && min_peak_ratio < 1e3)) {
    return fail("min_peak_ratio must be in [1, 1000)");
  }
  if (!(peak_exclusion_px >= 1.0 && peak_exclusion_px <= 1e3)) {
    return fail("peak_exclusion_px must be in [1, 1000]");
  }
  if (!(max_search_radius_px > 0.0 && max_search_radius_px <= 1e5)) {
    return fail("max_search_radius_px must be in (0, 1e5]");
  }
  return true;
}

ScdMatcher::ScdMatcher(ScdOptions options) : options_(options) {
  if (!options_.IsValid(nullptr)) return;  // Match reports it.
  const double sigma = options_.gradient_sigma_px;
  std::vector<double> g{1.0};
  if (sigma > 0.0) {
    const int half = std::max(1, static_cast<int>(std::ceil(3.0 * sigma)));
    gauss_kernel_ = cv::getGaussianKernel(2 * half + 1, sigma, CV_32F);
    cv::Mat g64;
    gauss_kernel_.convertTo(g64, CV_64F);
    g.assign(g64.begin<double>(), g64.end<double>());
  }
  // Std of one Sobel component of the blurred image per unit of white image noise: the
  // separable kernel is (g * [-1 0 1]) x (g * [1 2 1]).
  noise_gain_ = std::sqrt(SumOfSquares(Convolve(g, {-1.0, 0.0, 1.0})) *
                          SumOfSquares(Convolve(g, {1.0, 2.0, 1.0})));
  // A mask edge must not reach a kept gradient through the blur (3 sigma) and Sobel (1 px).
  erode_px_ = static_cast<int>(g.size() / 2) + 2;
}

void ScdMatcher::ComputeField(const cv::Mat& image, const cv::Mat& mask, const cv::Rect& roi,
                              Field* out) {
  const int margin = std::max(erode_px_, gauss_kernel_.rows / 2 + 2);
  const cv::Rect ext =
      cv::Rect(roi.x - margin, roi.y - margin, roi.width + 2 * margin, roi.height + 2 * margin) &
      cv::Rect(0, 0, image.cols, image.rows);
  const cv::Rect inner(roi.x - ext.x, roi.y - ext.y, roi.width, roi.height);
  image(ext).convertTo(work_f32_, CV_32F);

  // Validity: the mask, minus non-finite samples of float input.
  bool have_mask = !mask.empty();
  if (have_mask) cv::compare(mask(ext), 0, work_mask_, cv::CMP_NE);
  if (image.depth() == CV_32F && !cv::checkRange(work_f32_, true)) {
    cv::Mat finite;
    cv::compare(cv::abs(work_f32_), std::numeric_limits<float>::max(), finite, cv::CMP_LE);
    if (have_mask) {
      cv::bitwise_and(work_mask_, finite, work_mask_);
    } else {
      work_mask_ = finite;
      have_mask = true;
    }
    work_f32_.setTo(0.0f, ~finite);
  }
  double noise_std = 0.0;
  if (have_mask) {
    // Fill the no-data area with the mean so its edge is a small step, then keep only pixels
    // that the blurred edge cannot reach.
    const double fill = cv::mean(work_f32_, work_mask_)[0];
    cv::bitwise_not(work_mask_, tmp_);
    work_f32_.setTo(fill, tmp_);
    cv::erode(work_mask_, tmp_,
              cv::getStructuringElement(cv::MORPH_RECT, cv::Size(2 * erode_px_ + 1, 1)));
    cv::erode(tmp_, work_mask_,
              cv::getStructuringElement(cv::MORPH_RECT, cv::Size(1, 2 * erode_px_ + 1)));
    if (options_.noise_floor_sigmas > 0.0) {
      noise_std = EstimateNoiseStd(work_f32_, work_mask_, &blurred_);
    }
  } else if (options_.noise_floor_sigmas > 0.0) {
    noise_std = EstimateNoiseStd(work_f32_, cv::Mat(), &blurred_);
  }

  if (gauss_kernel_.empty()) {
    work_f32_.copyTo(blurred_);
  } else {
    cv::sepFilter2D(work_f32_, blurred_, CV_32F, gauss_kernel_, gauss_kernel_, cv::Point(-1, -1),
                    0.0, cv::BORDER_REFLECT);
  }
  cv::Sobel(blurred_(inner), gx_, CV_32F, 1, 0, 3, 1.0, 0.0, cv::BORDER_ISOLATED);
  cv::Sobel(blurred_(inner), gy_, CV_32F, 0, 1, 3, 1.0, 0.0, cv::BORDER_ISOLATED);

  const float floor = static_cast<float>(options_.noise_floor_sigmas * noise_std * noise_gain_);
  const float floor_sq = floor * floor;
  const bool mask_out_flat = options_.flat_handling == ScdFlatHandling::kMaskOut;
  out->cos_w.create(roi.size(), CV_32F);
  out->sin_w.create(roi.size(), CV_32F);
  out->valid.create(roi.size(), CV_32F);
  if (mask_out_flat) out->den_w.create(roi.size(), CV_32F);
  double valid_px = 0.0, oriented_px = 0.0;
  for (int y = 0; y < roi.height; ++y) {
    const float* gx = gx_.ptr<float>(y);
    const float* gy = gy_.ptr<float>(y);
    const uint8_t* m = have_mask ? work_mask_.ptr<uint8_t>(y + inner.y) + inner.x : nullptr;
    float* c = out->cos_w.ptr<float>(y);
    float* s = out->sin_w.ptr<float>(y);
    float* v = out->valid.ptr<float>(y);
    float* d = mask_out_flat ? out->den_w.ptr<float>(y) : nullptr;
    int row_valid = 0, row_oriented = 0;
    for (int x = 0; x < roi.width; ++x) {
      const bool is_valid = m == nullptr || m[x] != 0;
      const float mag_sq = gx[x] * gx[x] + gy[x] * gy[x];
      const bool oriented = is_valid && mag_sq > floor_sq && mag_sq > 0.0f;
      const float inv = oriented ? 1.0f / std::sqrt(mag_sq) : 0.0f;
      c[x] = gx[x] * inv;
      s[x] = gy[x] * inv;
      v[x] = is_valid ? 1.0f : 0.0f;
      if (d) d[x] = oriented ? 1.0f : 0.0f;
      row_valid += is_valid;
      row_oriented += oriented;
    }
    valid_px += row_valid;
    oriented_px += row_oriented;
  }
  if (!mask_out_flat) out->den_w = out->valid;
  out->valid_px = valid_px;
  out->oriented_px = oriented_px;
}

void ScdMatcher::ForwardDft(const cv::Mat& src, int nonzero_rows, cv::Mat* spectrum) {
  auto& plan = dft_plans_[{src.cols, src.rows, 0, nonzero_rows}];
  if (!plan) plan = cv::hal::DFT2D::create(src.cols, src.rows, CV_32F, 1, 1, 0, nonzero_rows);
  spectrum->create(src.size(), CV_32F);
  plan->apply(src.data, src.step, spectrum->data, spectrum->step);
}

void ScdMatcher::InverseDft(const cv::Mat& spectrum, int output_rows, cv::Mat* out) {
  const int flags = cv::DFT_INVERSE | cv::DFT_REAL_OUTPUT;
  auto& plan = dft_plans_[{spectrum.cols, spectrum.rows, flags, output_rows}];
  if (!plan) {
    plan = cv::hal::DFT2D::create(spectrum.cols, spectrum.rows, CV_32F, 1, 1, flags, output_rows);
  }
  out->create(spectrum.size(), CV_32F);
  plan->apply(spectrum.data, spectrum.step, out->data, out->step);
}

ScdResult ScdMatcher::Match(const cv::Mat& base, const cv::Mat& base_mask, const cv::Mat& templ,
                            const cv::Mat& templ_mask, const Eigen::Vector2d& predicted_offset,
                            double search_radius_px) {
  ScdResult result;
  auto fail = [&result](Status status, const std::string& reason) {
    result.status = status;
    result.reason = reason;
    return result;
  };
  std::string error;
  if (!options_.IsValid(&error)) return fail(Status::kBadInput, "invalid ScdOptions: " + error);
  if (base.empty() || templ.empty()) {
    return fail(Status::kBadInput, base.empty() ? "base image is empty" : "template is empty");
  }
  if (!IsSupportedImage(base) || !IsSupportedImage(templ)) {
    return fail(Status::kBadInput, "images must be one channel CV_8U, CV_16U or CV_32F (base " +
                                       Describe(base) + ", template " + Describe(templ) + ")");
  }
  if (!IsSupportedMask(base_mask, base) || !IsSupportedMask(templ_mask, templ)) {
    return fail(Status::kBadInput,
                "masks must be empty or CV_8U one channel of their image's size (base mask " +
                    Describe(base_mask) + ", template mask " + Describe(templ_mask) + ")");
  }
  if (!predicted_offset.allFinite()) {
    return fail(Status::kBadInput, "predicted offset is not finite");
  }
  if (!std::isfinite(search_radius_px) || search_radius_px < 0.0 ||
      search_radius_px > options_.max_search_radius_px) {
    return fail(Status::kBadInput, "search radius must be in [0, max_search_radius_px]");
  }
  const double templ_valid_px =
      templ_mask.empty() ? static_cast<double>(templ.total()) : cv::countNonZero(templ_mask);
  if (templ_valid_px == 0) return fail(Status::kBadInput, "template mask has no valid pixel");
  if (!base_mask.empty() && cv::countNonZero(base_mask) == 0) {
    return fail(Status::kBadInput, "base mask has no valid pixel");
  }

  // Integer offsets of the (Chebyshev) search window that put the template over the base.
  const double lo_x =
      std::max(std::ceil(predicted_offset.x() - search_radius_px), 1.0 - templ.cols);
  const double hi_x =
      std::min(std::floor(predicted_offset.x() + search_radius_px), base.cols - 1.0);
  const double lo_y =
      std::max(std::ceil(predicted_offset.y() - search_radius_px), 1.0 - templ.rows);
  const double hi_y =
      std::min(std::floor(predicted_offset.y() + search_radius_px), base.rows - 1.0);
  if (lo_x > hi_x || lo_y > hi_y) {
    return fail(Status::kTooLittleOverlap,
                "no offset within the search radius puts the template over the base");
  }
  const int u0 = static_cast<int>(lo_x), u1 = static_cast<int>(hi_x);
  const int v0 = static_cast<int>(lo_y), v1 = static_cast<int>(hi_y);
  const int nu = u1 - u0 + 1, nv = v1 - v0 + 1;

  // Template pixels that can meet the base for some offset; base pixels they can meet.
  const cv::Rect templ_roi(
      cv::Point(std::max(0, -u1), std::max(0, -v1)),
      cv::Point(std::min(templ.cols, base.cols - u0), std::min(templ.rows, base.rows - v0)));
  const cv::Rect base_roi(cv::Point(std::max(0, templ_roi.x + u0), std::max(0, templ_roi.y + v0)),
                          cv::Point(std::min(base.cols, templ_roi.br().x + u1),
                                    std::min(base.rows, templ_roi.br().y + v1)));

  ComputeField(templ, templ_mask, templ_roi, &templ_field_);
  ComputeField(base, base_mask, base_roi, &base_field_);
  // Pure noise puts exp(-k^2/2) of the pixels over a floor of k sigmas (Rayleigh magnitude).
  const double floor_k = options_.noise_floor_sigmas;
  const double min_oriented =
      options_.min_oriented_fraction + 1.5 * std::exp(-0.5 * floor_k * floor_k);
  for (const Field* f : {&templ_field_, &base_field_}) {
    const char* which = f == &templ_field_ ? "template" : "base";
    if (f->valid_px == 0) {
      return fail(Status::kTooLittleOverlap,
                  std::string("no valid ") + which + " pixel where the images can overlap");
    }
    if (f->oriented_px < std::max(1.0, min_oriented * f->valid_px)) {
      std::ostringstream s;
      s << which << " is flat: " << f->oriented_px << " of " << f->valid_px
        << " valid pixels have a gradient above the noise floor";
      return fail(Status::kFlat, s.str());
    }
  }

  // Correlation c(j) = sum_p t(p) b'(p + j), j = 0..n-1, with the base shifted right by d so that
  // j = 0 is offset (u0, v0); the FFT size leaves no wrap-around for those j.
  const int dx = base_roi.x - (templ_roi.x + u0), dy = base_roi.y - (templ_roi.y + v0);
  const int fft_w = cv::getOptimalDFTSize(std::max(templ_roi.width + nu - 1, dx + base_roi.width));
  const int fft_h =
      cv::getOptimalDFTSize(std::max(templ_roi.height + nv - 1, dy + base_roi.height));
  const bool mask_out_flat = options_.flat_handling == ScdFlatHandling::kMaskOut;
  const int n_fields = mask_out_flat ? 4 : 3;
  auto transform = [&](const Field& f, const cv::Rect& place, cv::Mat* spectra) {
    const cv::Mat* sources[4] = {&f.cos_w, &f.sin_w, &f.valid, &f.den_w};
    for (int k = 0; k < n_fields; ++k) {
      pad_.create(fft_h, fft_w, CV_32F);
      pad_.setTo(0.0f);
      sources[k]->copyTo(pad_(place));
      ForwardDft(pad_, place.br().y, &spectra[k]);
    }
  };
  cv::Mat* spec_t = spec_t_;
  cv::Mat* spec_b = spec_b_;
  transform(templ_field_, cv::Rect(cv::Point(0, 0), templ_roi.size()), spec_t);
  transform(base_field_, cv::Rect(cv::Point(dx, dy), base_roi.size()), spec_b);
  cv::mulSpectrums(spec_b[0], spec_t[0], spec_num_, 0, true);
  cv::mulSpectrums(spec_b[1], spec_t[1], spec_den_, 0, true);
  spec_num_ += spec_den_;
  InverseDft(spec_num_, nv, &corr_num_);
  cv::mulSpectrums(spec_b[2], spec_t[2], spec_ovl_, 0, true);
  InverseDft(spec_ovl_, nv, &corr_ovl_);
  if (mask_out_flat) {
    cv::mulSpectrums(spec_b[3], spec_t[3], spec_den_, 0, true);
    InverseDft(spec_den_, nv, &corr_den_);
  }
  // Score inside the window; offsets with too little overlap are NaN-free -inf.
  const float inv_n = 1.0f / static_cast<float>(fft_w * fft_h);
  const float min_overlap =
      static_cast<float>(std::max(1.0, options_.min_overlap_fraction * templ_valid_px));
  constexpr float kRejected = -std::numeric_limits<float>::infinity();
  const bool significance = options_.peak_criterion == ScdPeakCriterion::kSignificance;
  score_.create(nv, nu, CV_32F);
  int best_x = -1, best_y = -1;
  float best = kRejected;
  for (int j = 0; j < nv; ++j) {
    const float* num = corr_num_.ptr<float>(j);
    const float* ovl = corr_ovl_.ptr<float>(j);
    const float* den = mask_out_flat ? corr_den_.ptr<float>(j) : ovl;
    float* out = score_.ptr<float>(j);
    for (int i = 0; i < nu; ++i) {
      const float overlap = ovl[i] * inv_n, weight = den[i] * inv_n;
      float s = kRejected;
      if (overlap >= min_overlap && weight >= 0.5f) {
        s = significance ? num[i] / std::sqrt(den[i] * inv_n) : num[i] / den[i];
      }
      out[i] = s;
      if (s > best) {
        best = s;
        best_x = i;
        best_y = j;
      }
    }
  }
  if (best_x < 0) {
    std::ostringstream s;
    s << "no offset in the search window overlaps at least " << options_.min_overlap_fraction
      << " of the template's " << templ_valid_px << " valid pixels";
    return fail(Status::kTooLittleOverlap, s.str());
  }

  // Best local maximum outside the peak's neighbourhood.
  const double excl_sq = options_.peak_exclusion_px * options_.peak_exclusion_px;
  float second = kRejected;
  for (int j = 0; j < nv; ++j) {
    for (int i = 0; i < nu; ++i) {
      const float s = score_.at<float>(j, i);
      if (s <= second || s == kRejected) continue;
      const double ddx = i - best_x, ddy = j - best_y;
      if (ddx * ddx + ddy * ddy <= excl_sq) continue;
      bool is_max = true;
      for (int b = std::max(0, j - 1); b <= std::min(nv - 1, j + 1) && is_max; ++b) {
        for (int a = std::max(0, i - 1); a <= std::min(nu - 1, i + 1); ++a) {
          if (score_.at<float>(b, a) > s) {
            is_max = false;
            break;
          }
        }
      }
      if (is_max) second = s;
    }
  }

  auto at = [&](int i, int j) { return static_cast<double>(score_.at<float>(j, i)); };
  double sub_x = 0.0, sub_y = 0.0;
  if (best_x > 0 && best_x + 1 < nu && at(best_x - 1, best_y) > kRejected &&
      at(best_x + 1, best_y) > kRejected) {
    sub_x = RefineAxis(options_.subpixel, at(best_x - 1, best_y), best, at(best_x + 1, best_y));
  }
  if (best_y > 0 && best_y + 1 < nv && at(best_x, best_y - 1) > kRejected &&
      at(best_x, best_y + 1) > kRejected) {
    sub_y = RefineAxis(options_.subpixel, at(best_x, best_y - 1), best, at(best_x, best_y + 1));
  }
  const int peak_u = u0 + best_x, peak_v = v0 + best_y;
  result.offset = Eigen::Vector2d(peak_u + sub_x, peak_v + sub_y);
  {
    const float num = corr_num_.at<float>(best_y, best_x);
    const float den = (mask_out_flat ? corr_den_ : corr_ovl_).at<float>(best_y, best_x);
    result.score = std::clamp(static_cast<double>(num) / den, -1.0, 1.0);
  }
  constexpr double kMaxRatio = 1e3;  // Reported when no other peak scores above zero.
  result.peak_ratio =
      second > 0.0f ? std::min(kMaxRatio, best / static_cast<double>(second)) : kMaxRatio;

  // Overlap at the integer peak, counted on the masks as given (not eroded).
  const cv::Rect in_templ =
      cv::Rect(0, 0, templ.cols, templ.rows) & cv::Rect(-peak_u, -peak_v, base.cols, base.rows);
  const cv::Rect in_base = in_templ + cv::Point(peak_u, peak_v);
  if (templ_mask.empty() && base_mask.empty()) {
    result.overlap_px = in_templ.area();
  } else if (templ_mask.empty()) {
    result.overlap_px = cv::countNonZero(base_mask(in_base));
  } else if (base_mask.empty()) {
    result.overlap_px = cv::countNonZero(templ_mask(in_templ));
  } else {
    cv::bitwise_and(templ_mask(in_templ), base_mask(in_base), tmp_);
    result.overlap_px = cv::countNonZero(tmp_);
  }
  result.overlap_fraction = result.overlap_px / templ_valid_px;

  if (!(best > 0.0f)) {
    return fail(Status::kAmbiguous, "no offset has a positive SCD score");
  }
  if (result.peak_ratio < options_.min_peak_ratio) {
    std::ostringstream s;
    s << "peak ratio " << result.peak_ratio << " is under " << options_.min_peak_ratio
      << " (SCD score " << result.score << ")";
    return fail(Status::kAmbiguous, s.str());
  }
  result.status = Status::kOk;
  return result;
}

}  // namespace irmosaic
