// Test helper for the QGIS tests: writes a store in stages like a flight would.
//   store_writer STORE 1   creates STORE with a first strip of frames, publishes, exports
//                          STORE/../export.tif (COG, UTM);
//   store_writer STORE 2   resumes STORE and adds a second strip (the extent grows);
//   store_writer STORE 3   resumes STORE and paints and publishes until killed (crash test).
//   store_writer STORE 1 planned   as stage 1, with a planned extent covering stages 1 and 2
//                          (TileStore::SetPlannedBoundsPx), as `irmosaic run` writes from POS.
#include <cmath>
#include <filesystem>
#include <iostream>
#include <string>

#include "irmosaic/error.h"
#include "irmosaic/local_frame.h"
#include "irmosaic/mosaic_export.h"
#include "irmosaic/tile_store.h"

namespace {

constexpr double kLat0 = 47.2, kLon0 = 8.5, kGsd = 0.5;

// A synthetic thermal scene (16-bit counts) seen by a 640x512 frame whose top-left is at `origin`.
cv::Mat Scene(cv::Point origin) {
  cv::Mat image(512, 640, CV_16U);
  for (int y = 0; y < image.rows; ++y) {
    for (int x = 0; x < image.cols; ++x) {
      const double gx = origin.x + x, gy = origin.y + y;
      const double hot = std::exp(
          -(std::pow(std::fmod(gx, 300.0) - 150, 2) + std::pow(std::fmod(gy, 300.0) - 150, 2)) /
          800.0);
      image.at<uint16_t>(y, x) = static_cast<uint16_t>(7500 + 300 * std::sin(gx / 90.0) +
                                                       150 * std::cos(gy / 70.0) + 1200 * hot);
    }
  }
  return image;
}

// Feathered weight: 1 inside, falling to 0 over 32 pixels at the frame border.
cv::Mat Feather() {
  cv::Mat weight(512, 640, CV_32F);
  for (int y = 0; y < weight.rows; ++y) {
    for (int x = 0; x < weight.cols; ++x) {
      const int d = std::min({x, y, weight.cols - 1 - x, weight.rows - 1 - y});
      weight.at<float>(y, x) = std::min(1.0f, (d + 1) / 32.0f);
    }
  }
  return weight;
}

}  // namespace

int main(int argc, char** argv) {
  const bool planned = argc == 4 && std::string(argv[3]) == "planned";
  if (argc != 3 && !planned) {
    std::cerr << "usage: store_writer STORE 1|2|3 [planned]\n";
    return 2;
  }
  const std::string path = argv[1];
  const int stage = std::atoi(argv[2]);
  try {
    const irmosaic::LocalFrame frame(kLat0, kLon0);
    irmosaic::TileStoreOptions options;
    options.path = path;
    options.mode = stage == 1 ? irmosaic::TileStoreOptions::Mode::kCreate
                              : irmosaic::TileStoreOptions::Mode::kResume;
    auto store = irmosaic::TileStore::Open(options, {kLat0, kLon0, kGsd, frame.CrsWkt()});
    const cv::Mat weight = Feather();
    // Stage 1 covers x -320..2080, y -256..256; stage 2 y 200..712.
    if (planned) store->SetPlannedBoundsPx(cv::Rect(-320, -256, 2400, 968));
    if (stage == 3) {
      for (int i = 0;; ++i) {
        const cv::Point origin(-320 + (i % 12) * 160, 600 + (i / 12) * 200);
        store->Paint(Scene(origin), weight, origin);
        if (i % 4 == 3) store->RequestPublish();
      }
    }
    for (int i = 0; i < 12; ++i) {
      const int index = (stage - 1) * 12 + i;
      // Stage 1 flies east at row 0; stage 2 flies back west one strip further south.
      const cv::Point origin =
          stage == 1 ? cv::Point(-320 + i * 160, -256) : cv::Point(-320 + (11 - i) * 160, 200);
      store->Paint(Scene(origin), weight, origin);
      irmosaic::FrameRecord record;
      record.index = index;
      record.time_s = index * 0.04;
      const auto corner = [&](double x, double y) { return Eigen::Vector2d(x * kGsd, -y * kGsd); };
      record.footprint_m = {corner(origin.x, origin.y), corner(origin.x + 640, origin.y),
                            corner(origin.x + 640, origin.y + 512),
                            corner(origin.x, origin.y + 512)};
      record.status = "registered";
      record.inliers = 200;
      store->PutFrameRecord(record);
      if (i % 4 == 3) store->RequestPublish();
    }
    store->Close();
    if (stage == 1) {
      const std::filesystem::path out = std::filesystem::path(path).parent_path() / "export.tif";
      irmosaic::ExportMosaic(path, out.string(), {});
    }
  } catch (const irmosaic::Error& e) {
    std::cerr << "store_writer: " << e.what() << "\n";
    return 1;
  }
  return 0;
}
