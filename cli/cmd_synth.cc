// `irmosaic synth`: renders a simulated sweep flight with its ground truth into a folder.
#include <chrono>
#include <iomanip>
#include <iostream>

#include "args.h"
#include "commands.h"
#include "irmosaic/simulator.h"

namespace irmosaic::cli {

int RunSynth(int argc, char** argv) {
  Args args("synth",
            "Renders a simulated oblique sweep flight over a georeferenced ground raster:\n"
            "frames/ (16-bit TIFF), frames.csv, pos.csv (with POS errors), true_pos.csv,\n"
            "camera.json, truth.json (true placements) and flight.json (the options used).\n"
            "Options and defaults: docs/simulator.md.");
  args.Option("--config", "flight options, JSON (docs/simulator.md); defaults if not given", "",
              "FILE");
  args.Option("--out", "output folder", std::nullopt, "DIR");
  args.Option("--ground", "ground raster (overrides the config's ground_path)", "", "FILE");
  args.Option("--frames", "number of frames (overrides the config)", "", "N");
  args.Option("--seed", "random seed (overrides the config)", "", "N");
  args.Option("--bit-depth", "16 or 8 (overrides the config)", "", "BITS");
  args.Option("--format", "frame files: tif or png", "tif", "EXT");
  args.Option("--video", "also write an 8-bit video (.mkv/.avi: FFV1, .mjpg.avi: MJPG)", "",
              "FILE");
  args.Flag("--no-frames", "write POS, camera and truth only (no image files)");
  int exit_code = 0;
  if (!args.Parse(argc, argv, &exit_code)) return exit_code;

  SynthOptions options;
  if (!args.Get("--config").empty()) options = SynthOptions::LoadJson(args.Get("--config"));
  if (!args.Get("--ground").empty()) options.ground_path = args.Get("--ground");
  if (!args.Get("--frames").empty()) options.frame_count = args.GetInt("--frames");
  if (!args.Get("--seed").empty()) options.seed = static_cast<uint64_t>(args.GetInt("--seed"));
  if (!args.Get("--bit-depth").empty()) options.sensor.bit_depth = args.GetInt("--bit-depth");

  const auto start = std::chrono::steady_clock::now();
  const FlightSimulator sim(options);
  const FlightSummary& s = sim.summary();
  std::cerr << std::fixed << std::setprecision(2) << "synth: " << sim.frame_count()
            << " frames, origin " << std::setprecision(6) << sim.frame().origin_lat_deg() << ", "
            << sim.frame().origin_lon_deg() << std::setprecision(2) << ", gsd " << s.gsd_m
            << " m, speed " << s.speed_mps << " m/s, sweep " << s.sweep_min_deg << " .. "
            << s.sweep_max_deg << " deg (step " << s.sweep_step_deg << "), overlap along sweep "
            << 100 * s.along_sweep_overlap << " %, between sweeps " << 100 * s.between_sweep_overlap
            << " % (min " << 100 * s.between_sweep_overlap_min << " %)\n";
  WriteFlightOptions write;
  write.image_extension = args.Get("--format");
  write.video_path = args.Get("--video");
  write.write_frames = !args.Has("--no-frames");
  write.progress = [](int done, int total) {
    if (done % 10 == 0 || done == total) {
      std::cerr << "\rsynth: frame " << done << "/" << total << std::flush;
    }
  };
  sim.WriteFlight(args.Get("--out"), write);
  const double seconds =
      std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
  std::cerr << "\nsynth: wrote " << args.Get("--out") << " in " << std::setprecision(1) << seconds
            << " s\n";
  return 0;
}

}  // namespace irmosaic::cli
