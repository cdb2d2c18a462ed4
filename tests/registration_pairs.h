#pragma once

// Simulated registration pairs from real images (used by tests/registration_test.cc and
// bench/registration_bench.cc): two 640x512 frames cut from an upsampled real image with
// 15-25 % overlap, the template distorted by the homography of a random attitude error
// (K R K^-1, fx 2400 px), then gain/offset change, blur and noise.

#include <Eigen/Dense>
#include <algorithm>
#include <cmath>
#include <opencv2/imgproc.hpp>
#include <random>

namespace irmosaic::testing {

struct PairDegradation {
  double attitude_error_deg = 1.0;  // Each of the 3 angles uniform in +-this.
  double gain = 1.0, offset = 0.0;  // Template = gain * scene + offset.
  double blur_sigma_px = 0.0;       // Gaussian blur of both frames.
  double psnr_db = 0.0;             // Noise on both frames (8-bit peak 255); 0: none.
  double prior_error_px = 1.0;      // Coarse offset error, uniform in +-this per axis.
};

// The paper's distortions of a pair besides the attitude error (issue 5): gain 0.8 and offset 20
// on the template, blur sigma 2 px on both frames, and noise at `psnr_db` (0: none).
inline PairDegradation PaperDegradation(double psnr_db = 0.0) {
  PairDegradation d;
  d.gain = 0.8;
  d.offset = 20.0;
  d.blur_sigma_px = 2.0;
  d.psnr_db = psnr_db;
  return d;
}

struct SyntheticPair {
  cv::Mat base, templ;                 // CV_8U, 640x512.
  Eigen::Matrix3d base_from_template;  // Truth.
  Eigen::Vector2d prior_offset;        // Coarse translation as SCD would give it.
  cv::Rect2d overlap_in_template;      // Bounding box of the overlap, template pixels.
};

inline double NoiseSigmaForPsnr(double psnr_db) { return 255.0 / std::pow(10.0, psnr_db / 20.0); }

inline void Degrade(cv::Mat* image_f, double gain, double offset, double blur, double noise_sigma,
                    std::mt19937* rng, cv::Mat* out8) {
  cv::Mat f = *image_f * gain + offset;
  if (blur > 0) cv::GaussianBlur(f, f, cv::Size(), blur);
  if (noise_sigma > 0) {
    std::normal_distribution<float> noise(0.0f, static_cast<float>(noise_sigma));
    for (int y = 0; y < f.rows; ++y) {
      float* row = f.ptr<float>(y);
      for (int x = 0; x < f.cols; ++x) row[x] += noise(*rng);
    }
  }
  f.convertTo(*out8, CV_8U);  // Saturates like a real 8-bit sensor.
}

// `source`: CV_8U gray. `along_x`: overlap in the sweep (x) direction, else in y.
inline SyntheticPair MakePair(const cv::Mat& source, const PairDegradation& d, bool along_x,
                              std::mt19937* rng) {
  const int w = 640, h = 512;
  std::uniform_real_distribution<double> unit(-1.0, 1.0), overlap_draw(0.15, 0.25);
  const double overlap = overlap_draw(*rng);
  const Eigen::Vector2d shift = along_x ? Eigen::Vector2d(w * (1.0 - overlap), 0.0)
                                        : Eigen::Vector2d(0.0, h * (1.0 - overlap));
  // Attitude error: rotation about the camera axes through the principal point.
  const double k = M_PI / 180.0 * d.attitude_error_deg;
  // One draw a statement, x first: the operands of * are evaluated in an unspecified order
  // (GCC took the last first), and every compiler must draw the same pairs.
  const double about_x = k * unit(*rng), about_y = k * unit(*rng), about_z = k * unit(*rng);
  const Eigen::Matrix3d rotation = (Eigen::AngleAxisd(about_z, Eigen::Vector3d::UnitZ()) *
                                    Eigen::AngleAxisd(about_y, Eigen::Vector3d::UnitY()) *
                                    Eigen::AngleAxisd(about_x, Eigen::Vector3d::UnitX()))
                                       .toRotationMatrix();
  Eigen::Matrix3d camera;
  camera << 2400, 0, w / 2.0, 0, 2400, h / 2.0, 0, 0, 1;
  Eigen::Matrix3d translate = Eigen::Matrix3d::Identity();
  translate.topRightCorner<2, 1>() = shift;
  Eigen::Matrix3d truth = translate * camera * rotation * camera.inverse();
  truth /= truth(2, 2);

  // Source pixels per frame pixel so that both frames (+ margin) fit in the source.
  const double margin = 80.0;
  const double need_w = w + std::abs(shift.x()) + 2 * margin,
               need_h = h + std::abs(shift.y()) + 2 * margin;
  const double step = std::min({1.0, source.cols / need_w, source.rows / need_h});
  std::uniform_real_distribution<double> free_x(0.0, std::max(0.0, source.cols - need_w * step)),
      free_y(0.0, std::max(0.0, source.rows - need_h * step));
  Eigen::Matrix3d source_from_base;
  source_from_base << step, 0, free_x(*rng) + margin * step, 0, step, free_y(*rng) + margin * step,
      0, 0, 1;
  const Eigen::Matrix3d source_from_templ = source_from_base * truth;

  auto render = [&](const Eigen::Matrix3d& source_from_frame) {
    cv::Mat m(3, 3, CV_64F), out, source_f;
    for (int r = 0; r < 3; ++r) {
      for (int c = 0; c < 3; ++c) m.at<double>(r, c) = source_from_frame(r, c);
    }
    source.convertTo(source_f, CV_32F);
    cv::warpPerspective(source_f, out, m, cv::Size(w, h), cv::INTER_CUBIC | cv::WARP_INVERSE_MAP,
                        cv::BORDER_REFLECT);
    return out;
  };
  cv::Mat base_f = render(source_from_base), templ_f = render(source_from_templ);
  SyntheticPair pair;
  const double noise = d.psnr_db > 0 ? NoiseSigmaForPsnr(d.psnr_db) : 0.0;
  Degrade(&base_f, 1.0, 0.0, d.blur_sigma_px, noise, rng, &pair.base);
  Degrade(&templ_f, d.gain, d.offset, d.blur_sigma_px, noise, rng, &pair.templ);
  pair.base_from_template = truth;

  // Overlap: base corners pulled back into the template, clipped to the template.
  const Eigen::Matrix3d templ_from_base = truth.inverse();
  double x0 = 1e9, y0 = 1e9, x1 = -1e9, y1 = -1e9;
  for (const Eigen::Vector2d& c : {Eigen::Vector2d(0, 0), Eigen::Vector2d(w - 1, 0),
                                   Eigen::Vector2d(w - 1, h - 1), Eigen::Vector2d(0, h - 1)}) {
    const Eigen::Vector2d q = (templ_from_base * c.homogeneous()).hnormalized();
    x0 = std::min(x0, q.x()), y0 = std::min(y0, q.y()), x1 = std::max(x1, q.x()),
    y1 = std::max(y1, q.y());
  }
  x0 = std::max(x0, 0.0), y0 = std::max(y0, 0.0), x1 = std::min(x1, w - 1.0),
  y1 = std::min(y1, h - 1.0);
  pair.overlap_in_template = cv::Rect2d(x0, y0, x1 - x0, y1 - y0);
  const Eigen::Vector2d centre(0.5 * (x0 + x1), 0.5 * (y0 + y1));
  const Eigen::Vector2d local = (truth * centre.homogeneous()).hnormalized() - centre;
  const double prior_y = unit(*rng);  // Drawn first, as above.
  pair.prior_offset = local + d.prior_error_px * Eigen::Vector2d(unit(*rng), prior_y);
  return pair;
}

}  // namespace irmosaic::testing
