// Uses the installed irmosaic package: simulates a short flight, mosaics it with Mosaicker and
// prints the run's figures. docs/api.md shows the part between the [example] markers. Usage:
// consumer <empty folder for the store>
#include <irmosaic/error.h>
#include <irmosaic/mosaicker.h>
#include <irmosaic/simulator.h>
#include <irmosaic/version.h>

#include <array>
#include <cstdio>
#include <exception>
#include <opencv2/core.hpp>
#include <string>

int main(int argc, char** argv) {
  if (argc != 2) {
    std::fprintf(stderr, "usage: %s STORE_DIR\n", argv[0]);
    return 2;
  }
  try {
    irmosaic::SynthOptions synth;
    synth.frame_count = 12;
    synth.altitude_m = 400.0;
    synth.origin_lat_deg = 47.2;  // No ground raster: fractal terrain around this point.
    synth.origin_lon_deg = 8.5;
    irmosaic::FlightSimulator sim(synth);

    // [example]
    irmosaic::MosaickerOptions options;
    options.store_path = std::string(argv[1]) + "/flight.irmosaic";
    options.ground_height_m = synth.ground_height_m;
    irmosaic::Mosaicker mosaicker(options, sim.camera(), sim.MeasuredPos());
    int64_t last_generation = 0;  // The callback runs on this thread, inside Push/Finish.
    mosaicker.OnPublished([&](int64_t generation) { last_generation = generation; });
    for (int i = 0; i < sim.frame_count(); ++i) {
      const irmosaic::SimFrame frame = sim.Render(i);  // or: a video frame, a time, a pose
      const irmosaic::PushResult result = mosaicker.Push(frame.index, frame.time_s, frame.image);
      if (!result.placed()) std::printf("frame %d skipped: %s\n", i, result.reason.c_str());
    }
    mosaicker.Finish();  // final solve and publish

    // The mosaic as an image with its GDAL geotransform, and the per-frame records.
    const irmosaic::MosaicWindow window = mosaicker.ReadWindow(mosaicker.bounds_px());
    const std::array<double, 6>& gt = window.geotransform;
    std::printf("mosaic %dx%d px, %d painted, top-left (%.1f, %.1f) m, %.3f m pixels\n",
                window.image.cols, window.image.rows, cv::countNonZero(window.coverage), gt[0],
                gt[3], gt[1]);
    for (const irmosaic::FrameRecord& record : mosaicker.FrameRecords()) {
      std::printf("frame %lld: %s, %d inliers\n", static_cast<long long>(record.index),
                  record.status.c_str(), record.inliers);
    }
    const irmosaic::MosaickerSummary summary = mosaicker.summary();
    std::printf(
        "irmosaic %s: %lld frames pushed, %lld placed (%lld registered, %lld POS only), "
        "gsd %.3f m, generation %lld published\n",
        IRMOSAIC_VERSION_STRING, static_cast<long long>(summary.frames_pushed),
        static_cast<long long>(summary.frames_placed),
        static_cast<long long>(summary.frames_registered),
        static_cast<long long>(summary.frames_pos_only), summary.gsd_m,
        static_cast<long long>(last_generation));
    // [example end]
    const bool complete =
        summary.frames_placed == summary.frames_pushed && cv::countNonZero(window.coverage) > 0 &&
        static_cast<int64_t>(mosaicker.FrameRecords().size()) == summary.frames_placed &&
        last_generation == mosaicker.published_generation();
    return complete ? 0 : 1;
  } catch (const irmosaic::Error& e) {
    std::fprintf(stderr, "error: %s\n", e.what());
    return 1;
  }
}
