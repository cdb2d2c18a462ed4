// FlightSimulator::WriteFlight: a simulated flight on disk in the project's formats.
#include <cmath>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <iomanip>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/videoio.hpp>

#include "irmosaic/error.h"
#include "irmosaic/evaluator.h"
#include "irmosaic/simulator.h"

namespace irmosaic {

void FlightSimulator::WriteFlight(const std::string& dir, const WriteFlightOptions& options) const {
  namespace fs = std::filesystem;
  const std::string& ext = options.image_extension;
  if (ext != "tif" && ext != "png") {
    throw InputError({"WriteFlight", 0, 0, "image_extension"}, "unsupported extension " + ext,
                     "use tif or png");
  }
  std::error_code ec;
  fs::create_directories(fs::path(dir) / "frames", ec);
  if (ec) throw OutputError("cannot create " + dir + "/frames: " + ec.message());

  camera().SaveJson((fs::path(dir) / "camera.json").string());
  MeasuredPos().WriteCsv((fs::path(dir) / "pos.csv").string());
  TruePosTrack().WriteCsv((fs::path(dir) / "true_pos.csv").string());
  {
    std::ofstream flight((fs::path(dir) / "flight.json").string());
    flight << options_.ToJson() << "\n";
    if (!flight) throw OutputError("cannot write " + dir + "/flight.json");
  }
  Placements truth;
  truth.origin_lat_deg = frame_->origin_lat_deg();
  truth.origin_lon_deg = frame_->origin_lon_deg();
  truth.gsd_m = grid_.gsd_m;
  truth.image_width = options_.camera.width;
  truth.image_height = options_.camera.height;
  std::ofstream list((fs::path(dir) / "frames.csv").string());
  list << "index,time_s,file\n" << std::setprecision(17);
  const std::vector<int> params = ext == "tif" ? std::vector<int>{cv::IMWRITE_TIFF_COMPRESSION, 1}
                                               // Uncompressed: fast.
                                               : std::vector<int>{cv::IMWRITE_PNG_COMPRESSION, 1};
  cv::VideoWriter video;
  if (!options.video_path.empty()) {
    const bool mjpg = options.video_path.size() > 9 &&
                      options.video_path.substr(options.video_path.size() - 9) == ".mjpg.avi";
    const int fourcc = mjpg ? cv::VideoWriter::fourcc('M', 'J', 'P', 'G')
                            : cv::VideoWriter::fourcc('F', 'F', 'V', '1');
    video.open(options.video_path, fourcc, options_.fps,
               cv::Size(options_.camera.width, options_.camera.height), false);
    if (!video.isOpened()) throw OutputError("cannot open the video " + options.video_path);
  }
  for (int i = 0; i < frame_count(); ++i) {
    const SimFrame f = Render(i);
    char name[32];
    std::snprintf(name, sizeof(name), "frames/%06d.%s", i, ext.c_str());
    if (options.write_frames && !cv::imwrite((fs::path(dir) / name).string(), f.image, params)) {
      throw OutputError("cannot write " + dir + "/" + name);
    }
    if (video.isOpened()) {
      cv::Mat eight;
      f.image.convertTo(eight, CV_8U, f.image.depth() == CV_16U ? 1.0 / 256.0 : 1.0);
      video.write(eight);
    }
    if (options.write_frames) list << i << "," << f.time_s << "," << name << "\n";
    truth.frames.push_back({i, f.time_s, f.true_mosaic_from_image});
    if (options.progress) options.progress(i + 1, frame_count());
  }
  if (!list) throw OutputError("cannot write " + dir + "/frames.csv");
  truth.SaveJson((fs::path(dir) / "truth.json").string());

  // The baseline a pipeline starts from: placements from the logged POS alone, on the grid a
  // run would use (origin at the first logged record), so `irmosaic eval` has a reference.
  const PosRecord first = MeasuredPosRecord(0);
  const LocalFrame run_frame(first.lat_deg, first.lon_deg);
  Placements pos_only;
  pos_only.origin_lat_deg = first.lat_deg;
  pos_only.origin_lon_deg = first.lon_deg;
  pos_only.gsd_m = grid_.gsd_m;
  for (int i = 0; i < frame_count(); ++i) {
    const FrameGeometry g = ComputeFrameGeometry(
        options_.camera, PoseFromRecord(MeasuredPosRecord(i)), run_frame, grid_, flat_ground_);
    if (g.ok) pos_only.frames.push_back({i, i / options_.fps, g.mosaic_from_image});
  }
  pos_only.SaveJson((fs::path(dir) / "pos_only.json").string());

  // The neighbours a pipeline registers, with their true base_from_template: the previous
  // frame of the same sweep and the frame at the same angle in the previous sweep.
  std::vector<PairHomography> pairs;
  const int n = options_.frames_per_sweep;
  for (int i = 1; i < frame_count(); ++i) {
    const Eigen::Matrix3d& template_h = truth.frames[i].mosaic_from_image;
    if (i % n != 0) {
      pairs.push_back({i - 1, i, truth.frames[i - 1].mosaic_from_image.inverse() * template_h});
    }
    for (int j = (i / n - 1) * n; j >= 0 && j < (i / n) * n; ++j) {
      if (std::abs(SweepAngleDeg(j) - SweepAngleDeg(i)) < 1e-9) {
        pairs.push_back({j, i, truth.frames[j].mosaic_from_image.inverse() * template_h});
      }
    }
  }
  SavePairsJson(pairs, (fs::path(dir) / "truth_pairs.json").string());
}

}  // namespace irmosaic
