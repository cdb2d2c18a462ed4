// Fine registration diagnosis (issue 5): where the error of a noisy pair comes from.
// For the test's simulated pairs it prints, per pair: the Cramer-Rao bound of a dense
// homography fit over the overlap (clean gradients, white noise on both frames), the tie
// points' error against the truth (count, RMS, mean = bias), the corner RMSE of a least-squares
// homography on the good tie points (oracle inlier set), and the pipeline's corner RMSE.
// Usage: registration_diag_bench [--psnr DB] [--blur S] [--pairs N] [--seed S]
#include <Eigen/Dense>
#include <algorithm>
#include <cmath>
#include <cstdio>
#include <cstring>
#include <ctime>
#include <opencv2/calib3d.hpp>
#include <opencv2/core/utility.hpp>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>
#include <random>

#include "../tests/registration_pairs.h"
#include "irmosaic/registration.h"
#include "test_data.h"

namespace {

using irmosaic::testing::MakePair;
using irmosaic::testing::PairDegradation;

// Predicted corner RMSE (px) of the best unbiased dense homography estimate: Fisher
// information sum J^T J / (2 sigma^2) over overlap pixels, J = grad I * dw/dh (8 params).
double DenseBound(const cv::Mat& templ8, const Eigen::Matrix3d& truth, const cv::Rect2d& overlap,
                  double sigma) {
  cv::Mat f, gx, gy;
  templ8.convertTo(f, CV_32F);
  cv::Sobel(f, gx, CV_32F, 1, 0, 3, 1.0 / 8);
  cv::Sobel(f, gy, CV_32F, 0, 1, 3, 1.0 / 8);
  // Gradient of the base at the warped point ~ template gradient (near-translation warp).
  Eigen::Matrix<double, 8, 8> info = Eigen::Matrix<double, 8, 8>::Zero();
  const double cx = overlap.x + overlap.width / 2, cy = overlap.y + overlap.height / 2;
  for (int y = static_cast<int>(overlap.y) + 1; y < overlap.y + overlap.height - 1; ++y) {
    for (int x = static_cast<int>(overlap.x) + 1; x < overlap.x + overlap.width - 1; ++x) {
      const double u = (x - cx) / 100.0, v = (y - cy) / 100.0;
      const double ix = gx.at<float>(y, x), iy = gy.at<float>(y, x);
      Eigen::Matrix<double, 8, 1> j;
      // Homography around identity in centred coordinates scaled by 100 px: x' = x + ...
      j << ix * u, ix * v, ix, iy * u, iy * v, iy, -(ix * u + iy * v) * u, -(ix * u + iy * v) * v;
      j *= 100.0;  // Pixels per unit of the (100-px scaled) parameters.
      info += j * j.transpose();
    }
  }
  info /= 2.0 * sigma * sigma;
  const Eigen::Matrix<double, 8, 8> cov = info.inverse();
  double var = 0;
  for (const Eigen::Vector2d& c :
       {Eigen::Vector2d(overlap.x, overlap.y), Eigen::Vector2d(overlap.br().x, overlap.y),
        Eigen::Vector2d(overlap.br().x, overlap.br().y),
        Eigen::Vector2d(overlap.x, overlap.br().y)}) {
    const double u = (c.x() - cx) / 100.0, v = (c.y() - cy) / 100.0;
    Eigen::Matrix<double, 2, 8> jc;
    jc << u, v, 1, 0, 0, 0, -u * u, -u * v, 0, 0, 0, u, v, 1, -u * v, -v * v;
    jc *= 100.0;  // Params are per 100 px.
    var += (jc * cov * jc.transpose()).trace();
  }
  (void)truth;
  return std::sqrt(var / 4.0);
}

}  // namespace

int main(int argc, char** argv) {
  double psnr = 20, blur = 2;
  int pairs_per_source = 8;
  unsigned seed = 22;
  irmosaic::FineRegistrationOptions options;
  for (int i = 1; i + 1 < argc; ++i) {
    if (!std::strcmp(argv[i], "--psnr"))
      psnr = std::atof(argv[++i]);
    else if (!std::strcmp(argv[i], "--blur"))
      blur = std::atof(argv[++i]);
    else if (!std::strcmp(argv[i], "--pairs"))
      pairs_per_source = std::atoi(argv[++i]);
    else if (!std::strcmp(argv[i], "--seed"))
      seed = static_cast<unsigned>(std::atoi(argv[++i]));
    else if (!std::strcmp(argv[i], "--finest"))
      options.dense_finest_level = std::atoi(argv[++i]);
    else if (!std::strcmp(argv[i], "--coarsest"))
      options.dense_coarsest_level = std::atoi(argv[++i]);
    else if (!std::strcmp(argv[i], "--prior-linear"))
      options.prior_linear_sigma = std::atof(argv[++i]);
    else if (!std::strcmp(argv[i], "--prior-persp"))
      options.prior_perspective_sigma_per_px = std::atof(argv[++i]);
    else if (!std::strcmp(argv[i], "--grad-sigma"))
      options.dense_gradient_sigma = std::atof(argv[++i]);
    else if (!std::strcmp(argv[i], "--joint"))
      options.joint_refinement = std::atoi(argv[++i]);
    else if (!std::strcmp(argv[i], "--lsm-iter"))
      options.lsm.max_iterations = std::atoi(argv[++i]);
    else if (!std::strcmp(argv[i], "--keys"))
      options.keypoints.max_points = std::atoi(argv[++i]);
    else if (!std::strcmp(argv[i], "--dense-iter"))
      options.dense_iterations = std::atoi(argv[++i]);
    else if (!std::strcmp(argv[i], "--max-dense-sigma"))
      options.max_dense_sigma_px = std::atof(argv[++i]);
  }
  cv::setNumThreads(1);
  const char* sources[] = {"geotiff/UTM2GTIF.tiff", "geotiff/naip/m_4709963_se_14_1_20090818.tif",
                           "geotiff/naip/m_4709963_se_14_1_20190904.tif"};
  PairDegradation d;
  d.gain = 0.8, d.offset = 20, d.blur_sigma_px = blur, d.psnr_db = psnr;
  PairDegradation clean_d = d;
  clean_d.psnr_db = 0;
  const double sigma = psnr > 0 ? irmosaic::testing::NoiseSigmaForPsnr(psnr) : 0.5;
  irmosaic::FineRegistrationOptions no_dense = options;
  no_dense.dense_refinement = false;
  irmosaic::FineRegistrar registrar(options), plain(no_dense);
  std::mt19937 rng(seed);
  std::printf("%-4s %-5s %7s %6s %5s %7s %7s %7s %7s %8s %8s %8s %6s %6s %6s\n", "pair", "ovl",
              "bound", "keys", "ties", "tie_rms", "bias_x", "bias_y", "good", "oracle", "nodense",
              "ours", "joint", "dsigma", "dpix");
  int n = 0, within = 0, accepted = 0, under_bound = 0;
  std::vector<double> all;
  double cpu_ms = 0;
  for (const char* name : sources) {
    const cv::Mat source =
        cv::imread(irmosaic::testing::SharedDataPath(name), cv::IMREAD_GRAYSCALE);
    for (int i = 0; i < pairs_per_source; ++i, ++n) {
      std::mt19937 copy = rng;
      const auto pair = MakePair(source, d, i % 2 == 0, &rng);
      const auto clean = MakePair(source, clean_d, i % 2 == 0, &copy);
      const double bound =
          DenseBound(clean.templ, pair.base_from_template, pair.overlap_in_template, sigma);
      timespec t0, t1;
      clock_gettime(CLOCK_THREAD_CPUTIME_ID, &t0);
      const auto r = registrar.Register(pair.base, {}, pair.templ, {}, pair.prior_offset);
      clock_gettime(CLOCK_THREAD_CPUTIME_ID, &t1);
      cpu_ms += (t1.tv_sec - t0.tv_sec) * 1e3 + (t1.tv_nsec - t0.tv_nsec) * 1e-6;
      double sq = 0;
      Eigen::Vector2d bias = Eigen::Vector2d::Zero();
      std::vector<cv::Point2d> from, to;
      for (const auto& t : r.tie_points) {
        const Eigen::Vector2d e =
            t.in_base - (pair.base_from_template * t.in_template.homogeneous()).hnormalized();
        sq += e.squaredNorm();
        bias += e;
        if (e.norm() < 1.0) {
          from.emplace_back(t.in_template.x(), t.in_template.y());
          to.emplace_back(t.in_base.x(), t.in_base.y());
        }
      }
      const int ties = static_cast<int>(r.tie_points.size());
      double oracle = NAN;
      if (from.size() >= 4) {
        const cv::Mat h = cv::findHomography(from, to, 0);
        if (!h.empty()) {
          Eigen::Matrix3d e;
          for (int a = 0; a < 3; ++a)
            for (int b = 0; b < 3; ++b) e(a, b) = h.at<double>(a, b);
          oracle = irmosaic::CornerRmse(e, pair.base_from_template, pair.overlap_in_template);
        }
      }
      const auto r0 = plain.Register(pair.base, {}, pair.templ, {}, pair.prior_offset);
      const double before =
          r0.ok() ? irmosaic::CornerRmse(r0.base_from_template, pair.base_from_template,
                                         pair.overlap_in_template)
                  : NAN;
      const double ours = r.ok() || r.dense_pixels > 0
                              ? irmosaic::CornerRmse(r.base_from_template, pair.base_from_template,
                                                     pair.overlap_in_template)
                              : NAN;
      accepted += r.ok();
      within += r.ok() && ours < 0.3;
      under_bound += bound < 0.3;
      all.push_back(std::isnan(ours) ? 1e9 : ours);
      std::printf(
          "%-4d %-5s %7.3f %6d %5d %7.3f %7.3f %7.3f %7d %8.3f %8.3f %8.3f %6d %6.3f %6d %s\n", n,
          i % 2 == 0 ? "x" : "y", bound, r.keypoints, ties, ties ? std::sqrt(sq / ties) : NAN,
          ties ? bias.x() / ties : NAN, ties ? bias.y() / ties : NAN, static_cast<int>(from.size()),
          oracle, before, ours, r.joint_patches, r.dense_sigma_px, r.dense_pixels,
          r.ok() ? "" : r.reason.c_str());
    }
  }
  std::sort(all.begin(), all.end());
  std::printf(
      "pairs %d, accepted %d, accepted within 0.3 px %d, median error %.3f, bound < 0.3 px: %d, "
      "cpu %.2f ms/pair\n",
      n, accepted, within, all.empty() ? NAN : all[all.size() / 2], under_bound, cpu_ms / n);
  return 0;
}
