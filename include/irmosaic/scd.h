#pragma once

#include <Eigen/Core>
#include <cstdint>
#include <map>
#include <opencv2/core.hpp>
#include <opencv2/core/hal/hal.hpp>
#include <string>
#include <tuple>
#include <vector>

#include "irmosaic/export.h"

namespace irmosaic {

// Coarse translation between two orthoimages by masked SCD (sum of cosine differences of
// gradient orientation), correlated in the frequency domain. See docs/matching.md, "SCD".
//
// Usage:
//   ScdMatcher matcher;                       // one per thread, reused for every pair
//   ScdResult r = matcher.Match(base, base_mask, templ, templ_mask, predicted, 64.0);
//   if (r.ok()) use(r.offset);                // template pixel p <-> base pixel p + r.offset
//   else log(r.reason);

// What a pixel whose gradient magnitude is under the noise floor contributes.
enum class ScdFlatHandling {
  kZero,     // Counts as overlap (denominator) with a zero orientation vector (numerator).
  kMaskOut,  // Excluded from numerator and denominator, as if outside the mask.
  kSoft,     // Like kZero, but every pixel's unit vector is weighted by m^2 / (m^2 + floor^2).
};

// How the integer peak is refined to sub-pixel.
enum class ScdSubpixel {
  kParabola,  // 3-point quadratic fit per axis.
  kGaussian,  // 3-point fit of a Gaussian (quadratic on log score) per axis; parabola fallback.
};

// What the peak search maximises.
enum class ScdPeakCriterion {
  kScd,           // The masked SCD itself, sum cos / overlap (paper).
  kSignificance,  // sum cos / sqrt(overlap): SCD in units of its noise, so that a small
                  // overlap, whose SCD is noisier, must agree better to win.
};

struct ScdOptions {
  double gradient_sigma_px = 3.0;      // Gaussian pre-blur before gradients (3: measured, docs)
  double min_overlap_fraction = 0.05;  // of the template's valid pixels; smaller overlaps rejected
  // Gradient magnitudes under noise_floor_sigmas * (std of one gradient component of pure image
  // noise) carry no orientation. The image noise std is estimated per image (Immerkaer), so the
  // floor follows gain changes; 0 disables the floor.
  double noise_floor_sigmas = 2.0;
  ScdFlatHandling flat_handling = ScdFlatHandling::kZero;
  // Oriented pixels (template or base) fewer than this fraction of the valid pixels, on top of
  // 1.5 x the fraction pure noise reaches (Rayleigh: exp(-k^2/2), k = noise_floor_sigmas; the
  // measured fraction is a little higher, see docs/matching.md) -> kFlat.
  double min_oriented_fraction = 0.01;
  // Peak over the best local maximum farther than peak_exclusion_px (pixels of the searched,
  // possibly reduced, images) from it, both measured by peak_criterion; below -> kAmbiguous.
  // The ratio is reported as 1000 when no other peak is positive.
  double min_peak_ratio = 1.05;
  double peak_exclusion_px = 4.0;
  ScdSubpixel subpixel = ScdSubpixel::kParabola;
  // After the 3-point fit on integer offsets, fit again on offsets +-subpixel_step_px around
  // it, evaluated on the base gradients resampled (cubic) at those sub-pixel shifts: removes
  // most of the fit's bias on a peak that is not a parabola. 0 disables (5 evaluations fewer).
  double subpixel_step_px = 0.4;
  // The refit moves the first estimate by at most this much: on clean pairs it corrects the
  // 3-point fit's shape bias (under 0.2 px measured); a larger move under noise follows the
  // unweighted SCD's own, noisier peak (see magnitude_weight_cap; docs/matching.md).
  double subpixel_refit_max_px = 0.2;
  ScdPeakCriterion peak_criterion = ScdPeakCriterion::kScd;
  // Confidence weighting of the search: each oriented pixel's unit vector is weighted by
  // min(cap, m / median m), m its gradient magnitude and the median taken over the image's valid
  // pixels (so gain cancels). Under noise, weak gradients have random orientation; weighting
  // them less moves the SCD maximum much less (docs/matching.md). Used for the coarse FFT search
  // and the integer climb; the sub-pixel refit and the reported score use unit vectors (paper's
  // SCD; with pyramid_factor 1 the score is the weighted one). 0 = unit vectors throughout.
  double magnitude_weight_cap = 4.0;
  // Coarse-to-fine: the FFT search runs on images reduced by this factor (1, 2, 4 or 8; 1 = FFT
  // at full resolution), with coarse_gradient_sigma_px as pre-blur there; the peak is then
  // refined at full resolution (gradient_sigma_px) by direct SCD evaluation around it.
  int pyramid_factor = 4;
  double coarse_gradient_sigma_px = 1.0;
  // The full-resolution refinement (integer climb, sub-pixel fits, reported score) takes the
  // template's gradients on every fine_template_step-th row and column only (1 or 2); the base
  // stays at every pixel, so all integer offsets are still reachable. After the
  // gradient_sigma_px pre-blur the gradients are band-limited far below the half-rate
  // sampling's Nyquist frequency, so the criterion loses little (docs/matching.md) at about a
  // quarter of the template fields and dot products.
  int fine_template_step = 2;
  // With pyramid_factor above 1: refine the coarse peak at full resolution (integer climb,
  // sub-pixel fits, the reported score). Off, the result is the coarse peak with its
  // sub-pixel fit, scaled up, and score is 0; status and peak_ratio are the same. For a caller
  // whose fine registration refines the translation anyway: at pyramid_factor 4 the coarse
  // peak was within 3.2 px wherever the refined one was within 1 px (ScdTest, 48 hard pairs).
  bool refine_at_full_resolution = true;
  // Search radius above this is refused (kBadInput) to bound time and memory.
  double max_search_radius_px = 1024.0;

  // True when every field is in range; otherwise false with a message in *error (if not null).
  bool IsValid(std::string* error) const;
};

struct ScdResult {
  enum class Status { kOk, kTooLittleOverlap, kAmbiguous, kFlat, kBadInput };
  Status status = Status::kBadInput;
  std::string reason;                                // human-readable, set when status != kOk
  Eigen::Vector2d offset = Eigen::Vector2d::Zero();  // sub-pixel; template p <-> base p + offset
  double score = 0.0;                                // masked SCD at the peak, in [-1, 1]
  double overlap_px = 0.0;                           // valid overlapping pixels at the peak
  double overlap_fraction = 0.0;                     // overlap_px / template valid pixels
  double peak_ratio = 0.0;  // confidence: peak over the best peak outside its neighbourhood
  bool ok() const { return status == Status::kOk; }
};

// Printable name of a status ("ok", "too little overlap", ...).
IRMOSAIC_EXPORT const char* ToString(ScdResult::Status status);

// Reusable matcher: FFT plans/buffers and filter kernels kept between calls. Buffers are sized by
// the pair's reachable overlap, so they are reused (no allocation) when a pair repeats a
// geometry, and OpenCV's filters keep their own row scratch. Not thread-safe; one per thread.
class IRMOSAIC_EXPORT ScdMatcher {
 public:
  // Options are checked on each Match (invalid -> kBadInput with the reason).
  explicit ScdMatcher(ScdOptions options = {});

  // base/templ: CV_8U, CV_16U or CV_32F single channel; masks CV_8U (nonzero = valid) or empty
  // (= all valid), same size as their image; non-finite float pixels count as invalid. Searches
  // integer offsets within search_radius_px (Chebyshev: a square window) of predicted_offset,
  // then refines the peak to sub-pixel. Valid pixels are those of the mask eroded by
  // ceil(2 sigma) + 1 px, the image border counting as a mask edge, so that edges create no
  // gradients; the search's overlap test counts these, the reported overlap_px counts the masks
  // as given. peak_ratio comes from the coarse (reduced) search.
  ScdResult Match(const cv::Mat& base, const cv::Mat& base_mask, const cv::Mat& templ,
                  const cv::Mat& templ_mask, const Eigen::Vector2d& predicted_offset,
                  double search_radius_px);

  const ScdOptions& options() const { return options_; }

 private:
  using Status = ScdResult::Status;
  // Pre-blur kernel and what follows from it.
  struct Filter {
    cv::Mat gauss;            // empty: no blur
    double noise_gain = 1.0;  // std of a Sobel component of the blurred image per unit noise
    int erode_px = 0;         // how far a mask edge reaches through blur and Sobel
  };
  // Orientation field of an image region: weighted unit gradient, denominator weight, validity.
  struct Field {
    cv::Rect region;  // in its image's pixels
    int step = 1;     // plane sample (i, j) is pixel region.tl() + step * (i, j)
    cv::Mat cos_w, sin_w, den_w, valid;
    double valid_px = 0.0, oriented_px = 0.0;
    float floor_sq = 0.0f;  // squared gradient noise floor used
  };
  // Peak of the FFT search, in the coordinates of the images searched.
  struct Peak {
    cv::Point offset;
    Eigen::Vector2d subpixel = Eigen::Vector2d::Zero();
    double ratio = 0.0;
  };
  // Buffers of one pyramid level: kept apart so that sizes do not alternate between calls.
  struct Scratch {
    cv::Mat work_f32, work_mask, blurred, gx, gy, tmp, eroded;
    Field templ_field, base_field;
    Field templ_unit;  // unit-vector field of the template (fine level, weighting on)
  };
  // *noise_std: the image noise std to use, or negative to estimate it (then written back).
  // unit (optional): also the unit-vector field of the same gradients. step: sampling of the
  // field's planes (Field::step).
  void ComputeField(const Filter& filter, const cv::Mat& image, const cv::Mat& mask,
                    const cv::Rect& roi, Scratch* scratch, Field* out, double* noise_std,
                    Field* unit = nullptr, int step = 1);
  // Masked SCD over the integer window [lo, hi] (inclusive) by FFT; kOk or a failure in result.
  Status FftSearch(const Filter& filter, const cv::Mat& base, const cv::Mat& base_mask,
                   const cv::Mat& templ, const cv::Mat& templ_mask, double templ_valid_px,
                   cv::Point lo, cv::Point hi, Peak* peak, std::string* reason);
  // Hill-climbs the full-resolution criterion from `start` within [lo, hi]; sub-pixel peak.
  Status Refine(const cv::Mat& base, const cv::Mat& base_mask, const cv::Mat& templ,
                const cv::Mat& templ_mask, cv::Point start, cv::Point lo, cv::Point hi,
                int max_steps, Peak* peak, std::string* reason);
  // Criterion and SCD at one offset from the fine fields (false when nothing overlaps); the
  // template field may be sampled at a step, the base field is at every pixel.
  bool Evaluate(const Field& templ_field, const Field& base_field, cv::Point offset,
                double* criterion, double* scd) const;
  // Criterion at integer `offset` of the template's unit field against the fine base gradients
  // resampled (cubic) at a sub-pixel shift, normalised on the fly: they are band-limited by the
  // pre-blur, and blur and Sobel commute with the shift.
  // scd (optional): the unweighted SCD there.
  double EvaluateShifted(cv::Point offset, const Eigen::Vector2d& shift, double* scd = nullptr);
  // Fills a field's vectors and weights from gradients; validity already in out->valid.
  // weight_cap > 0: vectors weighted by min(weight_cap, m / median m) (magnitude_weight_cap).
  void Normalise(const cv::Mat& gx, const cv::Mat& gy, double weight_cap, Field* out);
  Status CheckFlat(const Field& f, const char* which, std::string* reason) const;
  void ForwardDft(const cv::Mat& src, int nonzero_rows, cv::Mat* spectrum);
  void InverseDft(const cv::Mat& spectrum, int output_rows, cv::Mat* out);

  ScdOptions options_;
  Filter fine_, coarse_;
  // Scratch, reused between calls.
  Scratch coarse_scratch_, fine_scratch_, shift_scratch_;
  cv::Mat shifted_gx_, shifted_gy_;
  // Vertical passes of the last resampling (EvaluateShifted), reused while its key holds.
  struct ShiftRows {
    bool valid = false;
    cv::Point origin;
    cv::Size count;
    int step = 1;
    double shift_y = 0.0;
    cv::Mat gx, gy;
  } shift_rows_;
  std::vector<uint8_t> erode_pad_;     // row scratch of the erosion and the reduction
  std::vector<float> reduce_sum_;      // row sums of the reduction (float images)
  std::vector<uint32_t> reduce_isum_;  // ... (integer images)
  std::vector<float> magnitudes_;      // sample for the median gradient magnitude
  cv::Mat base_small_, templ_small_, base_mask_small_, templ_mask_small_;
  cv::Mat pad_, spec_t_[4], spec_b_[4], spec_num_, spec_den_, spec_ovl_, corr_num_, corr_den_,
      corr_ovl_, score_;
  std::map<std::tuple<int, int, int, int>, cv::Ptr<cv::hal::DFT2D>> dft_plans_;
};

}  // namespace irmosaic
