// The evaluator's plot: RMSE (log scale) against frame index, one curve per run (paper Fig. 10).
#include <algorithm>
#include <cmath>
#include <iomanip>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>
#include <sstream>

#include "irmosaic/error.h"
#include "irmosaic/evaluator.h"

namespace irmosaic {
namespace {

const cv::Scalar kColours[] = {{200, 90, 20}, {30, 30, 200}, {40, 150, 40}, {160, 40, 160},
                               {0, 140, 200}, {120, 120, 0}, {90, 90, 90}};

std::string Format(double v) {
  std::ostringstream s;
  s << std::setprecision(3) << v;
  return s.str();
}

void Text(cv::Mat& img, const std::string& text, cv::Point at, double scale, int align = 0,
          const cv::Scalar& colour = {20, 20, 20}) {
  int base = 0;
  const cv::Size size = cv::getTextSize(text, cv::FONT_HERSHEY_SIMPLEX, scale, 1, &base);
  if (align == 1) at.x -= size.width / 2;  // Centred.
  if (align == 2) at.x -= size.width;      // Right-aligned.
  cv::putText(img, text, at, cv::FONT_HERSHEY_SIMPLEX, scale, colour, 1, cv::LINE_AA);
}

}  // namespace

void PlotRmseVsIndex(const std::vector<PlacementScore>& scores, const std::string& png_path,
                     const std::string& title) {
  const int width = 1200, height = 640;
  const int left = 100, right = 30, top = 60, bottom = 80;
  cv::Mat img(height, width, CV_8UC3, cv::Scalar(255, 255, 255));
  int index_min = 0, index_max = 1;
  double lo = 1.0, hi = 1.0;
  bool any = false;
  for (const PlacementScore& s : scores) {
    for (const FrameScore& f : s.frames) {
      if (!any) index_min = index_max = f.index;
      index_min = std::min(index_min, f.index);
      index_max = std::max(index_max, f.index);
      lo = std::min(lo, std::max(f.rmse_px, 1e-3));
      hi = std::max(hi, std::min(f.rmse_px, 1e6));
      any = true;
    }
  }
  if (index_max == index_min) ++index_max;
  const int dec_lo = static_cast<int>(std::floor(std::log10(lo)));
  const int dec_hi = std::max(dec_lo + 1, static_cast<int>(std::ceil(std::log10(hi))));
  const cv::Rect plot(left, top, width - left - right, height - top - bottom);
  auto x_of = [&](double index) {
    return plot.x + static_cast<int>(
                        std::lround((index - index_min) / (index_max - index_min) * plot.width));
  };
  auto y_of = [&](double rmse) {
    const double l = std::log10(std::clamp(rmse, std::pow(10.0, dec_lo), std::pow(10.0, dec_hi)));
    return plot.y + plot.height -
           static_cast<int>(std::lround((l - dec_lo) / (dec_hi - dec_lo) * plot.height));
  };
  // Grid: decades and their 2x, 5x; frame index ticks.
  for (int d = dec_lo; d <= dec_hi; ++d) {
    for (int m : {1, 2, 5}) {
      const double v = m * std::pow(10.0, d);
      if (v > std::pow(10.0, dec_hi) * 1.0001) continue;
      const int y = y_of(v);
      cv::line(img, {plot.x, y}, {plot.x + plot.width, y},
               m == 1 ? cv::Scalar(200, 200, 200) : cv::Scalar(235, 235, 235), 1);
      if (m == 1 || dec_hi - dec_lo <= 2) Text(img, Format(v), {plot.x - 8, y + 5}, 0.5, 2);
    }
  }
  const double span = index_max - index_min;
  const double raw_step = span / 8.0;
  const double mag = std::pow(10.0, std::floor(std::log10(raw_step)));
  double step = mag;
  for (double m : {1.0, 2.0, 5.0, 10.0}) {
    if (m * mag >= raw_step) {
      step = m * mag;
      break;
    }
  }
  for (double t = std::ceil(index_min / step) * step; t <= index_max; t += step) {
    const int x = x_of(t);
    cv::line(img, {x, plot.y}, {x, plot.y + plot.height}, cv::Scalar(235, 235, 235), 1);
    Text(img, Format(t), {x, plot.y + plot.height + 20}, 0.5, 1);
  }
  // The 1 px line: the paper's target.
  for (int x = plot.x; x < plot.x + plot.width; x += 12) {
    cv::line(img, {x, y_of(1.0)}, {std::min(x + 6, plot.x + plot.width), y_of(1.0)},
             cv::Scalar(0, 0, 0), 1);
  }
  cv::rectangle(img, plot, cv::Scalar(60, 60, 60), 1);
  for (size_t k = 0; k < scores.size(); ++k) {
    const cv::Scalar colour = kColours[k % std::size(kColours)];
    std::vector<cv::Point> pts;
    for (const FrameScore& f : scores[k].frames) pts.emplace_back(x_of(f.index), y_of(f.rmse_px));
    if (pts.size() == 1) cv::circle(img, pts[0], 3, colour, cv::FILLED);
    if (pts.size() > 1) cv::polylines(img, pts, false, colour, 2, cv::LINE_AA);
  }
  // Legend box, top left inside the plot, over the curves.
  const int legend_w = 620, legend_h = 12 + 22 * static_cast<int>(scores.size());
  const cv::Rect legend(plot.x + 8, plot.y + 6, legend_w, legend_h);
  cv::rectangle(img, legend, cv::Scalar(255, 255, 255), cv::FILLED);
  cv::rectangle(img, legend, cv::Scalar(180, 180, 180), 1);
  for (size_t k = 0; k < scores.size(); ++k) {
    const cv::Scalar colour = kColours[k % std::size(kColours)];
    const int ly = plot.y + 26 + 22 * static_cast<int>(k);
    const int lx = plot.x + 16;
    cv::line(img, {lx, ly - 5}, {lx + 30, ly - 5}, colour, 3);
    const PlacementScore& s = scores[k];
    Text(img,
         (s.name.empty() ? "run " + std::to_string(k + 1) : s.name) + ": median " +
             Format(s.rmse_px.median) + " px, p95 " + Format(s.rmse_px.p95) + " px, " +
             std::to_string(s.frames_scored) + " frames",
         {lx + 38, ly}, 0.5, 0, colour);
  }
  Text(img, "frame index", {plot.x + plot.width / 2, height - 25}, 0.65, 1);
  cv::Mat label(30, plot.height, CV_8UC3, cv::Scalar(255, 255, 255));
  Text(label, "RMSE per frame (truth mosaic pixels, log scale)", {plot.height / 2, 21}, 0.6, 1);
  cv::Mat rotated;
  cv::rotate(label, rotated, cv::ROTATE_90_COUNTERCLOCKWISE);
  rotated.copyTo(img(cv::Rect(10, plot.y, 30, plot.height)));
  Text(img, title.empty() ? "Placement error against the truth" : title, {width / 2, 35}, 0.75, 1);
  if (!cv::imwrite(png_path, img)) throw OutputError("cannot write the plot " + png_path);
}

}  // namespace irmosaic
