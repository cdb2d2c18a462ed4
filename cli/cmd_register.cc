// `irmosaic register`: registers two images (SCD coarse translation when built with SCD, fast
// LSM at key points, RANSAC homography) and prints the result as JSON.
#include <Eigen/Dense>
#include <cmath>
#include <iostream>
#include <nlohmann/json.hpp>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>
#include <sstream>

#include "args.h"
#include "commands.h"
#include "irmosaic/error.h"
#include "irmosaic/registration.h"

namespace irmosaic::cli {
namespace {

cv::Mat ReadGray(const std::string& path) {
  const cv::Mat image = cv::imread(path, cv::IMREAD_GRAYSCALE | cv::IMREAD_ANYDEPTH);
  if (image.empty()) {
    throw InputError(SourceLocation{path, 0, 0, ""}, "cannot read this image",
                     "give a path to an image OpenCV reads (PNG, TIFF, JPEG, ...; 8 or 16 bit)");
  }
  return image;
}

Eigen::Vector2d ParsePair(const std::string& text, const std::string& option) {
  std::istringstream in(text);
  double x = NAN, y = NAN;
  char comma = 0;
  in >> x >> comma >> y;
  if (!in || comma != ',' || !std::isfinite(x) || !std::isfinite(y)) {
    throw InputError(SourceLocation{"command line", 0, 0, option}, "'" + text + "' is not DX,DY",
                     "write two numbers separated by a comma, e.g. --prior 480,3.5");
  }
  return {x, y};
}

nlohmann::json Rows(const Eigen::Matrix3d& m) {
  nlohmann::json rows = nlohmann::json::array();
  for (int r = 0; r < 3; ++r) rows.push_back({m(r, 0), m(r, 1), m(r, 2)});
  return rows;
}

}  // namespace

int RunRegister(int argc, char** argv) {
  Args args("register",
            "Registers image B onto image A: coarse translation (SCD), fast least squares\n"
            "matching at key points of the overlap, RANSAC homography. Prints JSON with the\n"
            "status, the quality figures and the homographies, row-major 3x3, pixel centres at\n"
            "integers, x right, y down:\n"
            "  \"a_from_b\": maps B pixel coordinates to A pixel coordinates;\n"
            "  \"b_from_a\": its inverse, A pixel coordinates to B pixel coordinates.\n"
            "Exit code 0 when the pair is accepted, 4 when it is refused (see \"status\").");
  args.Positional("A", "base image (any one- or three-channel image OpenCV reads, 8/16 bit)");
  args.Positional("B", "template image, registered onto A");
  args.Option("--prior", "predicted position of B's top-left pixel in A's pixel coordinates", "",
              "DX,DY");
  args.Option("--radius", "search radius of the coarse match around the prior, pixels", "64", "R");
  int exit_code = 0;
  if (!args.Parse(argc, argv, &exit_code)) return exit_code;

  const cv::Mat a = ReadGray(args.Get("A"));
  const cv::Mat b = ReadGray(args.Get("B"));
  const double radius = args.GetDouble("--radius");
  if (!(radius >= 0.0 && radius <= 4096.0)) {
    throw InputError(SourceLocation{"command line", 0, 0, "--radius"}, "radius out of range",
                     "give a radius in [0, 4096] pixels");
  }
  nlohmann::json out;
#ifdef IRMOSAIC_HAS_SCD
  const Eigen::Vector2d prior = args.Get("--prior").empty()
                                    ? Eigen::Vector2d::Zero()
                                    : ParsePair(args.Get("--prior"), "--prior");
  PairRegistrar registrar;
  const PairRegistration r = registrar.Register(a, {}, b, {}, prior, radius);
  out["coarse"] = {{"method", "scd"},
                   {"status_ok", r.coarse.ok()},
                   {"reason", r.coarse.reason},
                   {"score", r.coarse.score},
                   {"peak_ratio", r.coarse.peak_ratio}};
#else
  // Built without SCD (issue 4): the prior is the coarse translation, or phase correlation of
  // equal-size images gives one.
  Eigen::Vector2d prior = Eigen::Vector2d::Zero();
  std::string coarse_method = "prior";
  if (!args.Get("--prior").empty()) {
    prior = ParsePair(args.Get("--prior"), "--prior");
  } else if (a.size() == b.size()) {
    cv::Mat fa, fb, window;
    a.convertTo(fa, CV_64F);
    b.convertTo(fb, CV_64F);
    cv::createHanningWindow(window, a.size(), CV_64F);
    const cv::Point2d shift = cv::phaseCorrelate(fb, fa, window);
    prior = {shift.x, shift.y};
    coarse_method = "phase_correlation";
  } else {
    throw InputError(SourceLocation{"command line", 0, 0, "--prior"},
                     "images of different sizes need a prior (this build has no SCD)",
                     "give --prior DX,DY");
  }
  FineRegistrar registrar;
  const PairRegistration r = registrar.Register(a, {}, b, {}, prior);
  out["coarse"] = {{"method", coarse_method}, {"radius_px_ignored", radius}};
#endif
  out["status"] = ToString(r.status);
  out["reason"] = r.reason;
  out["offset_px"] = {r.offset.x(), r.offset.y()};
  out["keypoints"] = r.keypoints;
  out["tie_points"] = r.tie_points.size();
  out["inliers"] = r.inliers;
  out["inlier_ratio"] = r.inlier_ratio;
  out["residual_rms_px"] = r.residual_rms_px;
  if (!r.tie_points.empty() && r.status != PairRegistration::Status::kRansacFailed &&
      r.status != PairRegistration::Status::kTooFewTiePoints) {
    out["a_from_b"] = Rows(r.base_from_template);
    out["b_from_a"] = Rows(r.base_from_template.inverse() / r.base_from_template.inverse()(2, 2));
  }
  std::cout << out.dump(1) << "\n";
  return r.ok() ? 0 : 4;
}

}  // namespace irmosaic::cli
