// Uses the installed irmosaic package: simulates a short flight, mosaics it with Mosaicker and
// prints the run's figures. Usage: consumer <empty folder for the store>
#include <irmosaic/error.h>
#include <irmosaic/mosaicker.h>
#include <irmosaic/simulator.h>
#include <irmosaic/version.h>

#include <cstdio>
#include <exception>
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

    irmosaic::MosaickerOptions options;
    options.store_path = std::string(argv[1]) + "/flight.irmosaic";
    options.ground_height_m = synth.ground_height_m;
    irmosaic::Mosaicker mosaicker(options, sim.camera(), sim.MeasuredPos());
    for (int i = 0; i < sim.frame_count(); ++i) {
      const irmosaic::SimFrame frame = sim.Render(i);
      const irmosaic::PushResult result = mosaicker.Push(frame.index, frame.time_s, frame.image);
      if (!result.placed()) std::printf("frame %d skipped: %s\n", i, result.reason.c_str());
    }
    mosaicker.Finish();

    const irmosaic::MosaickerSummary summary = mosaicker.summary();
    std::printf(
        "irmosaic %s: %lld frames pushed, %lld placed (%lld registered, %lld POS only), "
        "gsd %.3f m\n",
        IRMOSAIC_VERSION_STRING, static_cast<long long>(summary.frames_pushed),
        static_cast<long long>(summary.frames_placed),
        static_cast<long long>(summary.frames_registered),
        static_cast<long long>(summary.frames_pos_only), summary.gsd_m);
    return summary.frames_placed == summary.frames_pushed ? 0 : 1;
  } catch (const irmosaic::Error& e) {
    std::fprintf(stderr, "error: %s\n", e.what());
    return 1;
  }
}
