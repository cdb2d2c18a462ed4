// Rendering speed of the flight simulator, one core: prints a table and writes JSON.
//   simulator_bench [--frames N] [--json FILE]
#include <chrono>
#include <cstring>
#include <ctime>
#include <fstream>
#include <iomanip>
#include <iostream>
#include <nlohmann/json.hpp>
#include <opencv2/core.hpp>
#include <string>

#include "irmosaic/simulator.h"
#include "test_data.h"

namespace {

// CPU time of this process: on a machine shared with other jobs, wall time undercounts a core.
double CpuSeconds() {
  timespec ts{};
  clock_gettime(CLOCK_PROCESS_CPUTIME_ID, &ts);
  return static_cast<double>(ts.tv_sec) + 1e-9 * static_cast<double>(ts.tv_nsec);
}

struct Case {
  std::string name;
  irmosaic::SynthOptions options;
};

}  // namespace

int main(int argc, char** argv) {
  int frames = 1000;
  std::string json_path;
  for (int i = 1; i < argc; ++i) {
    if (!std::strcmp(argv[i], "--frames") && i + 1 < argc) frames = std::atoi(argv[++i]);
    if (!std::strcmp(argv[i], "--json") && i + 1 < argc) json_path = argv[++i];
  }
  cv::setNumThreads(1);  // One core, as the target says.

  irmosaic::SynthOptions base;
  base.frame_count = frames;
  base.origin_lat_deg = 47.2;
  base.origin_lon_deg = 8.5;
  std::vector<Case> cases;
  cases.push_back({"fractal ground, all effects, 16-bit", base});
  Case real{"UTM2GTIF ground, all effects, 16-bit", base};
  real.options.ground_path = irmosaic::testing::SharedDataPath("geotiff/UTM2GTIF.tiff");
  real.options.origin_lat_deg = real.options.origin_lon_deg = std::nan("");
  cases.push_back(real);
  Case clean{"fractal ground, no sensor effects", base};
  clean.options.sensor = {};
  clean.options.sensor.motion_blur = clean.options.sensor.vignetting = false;
  clean.options.sensor.gain_drift = clean.options.sensor.noise = false;
  clean.options.sensor.column_noise = clean.options.sensor.dead_pixels = false;
  clean.options.sensor.psf_sigma_px = 0.0;
  cases.push_back(clean);
  Case eight{"fractal ground, all effects, 8-bit", base};
  eight.options.sensor.bit_depth = 8;
  cases.push_back(eight);

  nlohmann::json results = nlohmann::json::array();
  std::cout << std::left << std::setw(42) << "case" << std::right << std::setw(10) << "frames"
            << std::setw(12) << "frames/s" << std::setw(12) << "ms/frame" << std::setw(14)
            << "CPU frames/s" << std::setw(14) << "tiles/frame" << std::setw(12) << "setup ms"
            << "\n";
  for (const Case& c : cases) {
    const auto t0 = std::chrono::steady_clock::now();
    irmosaic::FlightSimulator sim(c.options);
    const auto t1 = std::chrono::steady_clock::now();
    double checksum = 0.0;
    const double cpu0 = CpuSeconds();
    for (int i = 0; i < frames; ++i)
      checksum += static_cast<double>(cv::sum(sim.Render(i).image)[0]);
    const double cpu_s = CpuSeconds() - cpu0;
    const auto t2 = std::chrono::steady_clock::now();
    const double setup_ms = std::chrono::duration<double, std::milli>(t1 - t0).count();
    const double render_s = std::chrono::duration<double>(t2 - t1).count();
    const double fps = frames / render_s;
    const double tiles = static_cast<double>(sim.ground().tiles_generated()) / frames;
    std::cout << std::left << std::setw(42) << c.name << std::right << std::setw(10) << frames
              << std::setw(12) << std::fixed << std::setprecision(1) << fps << std::setw(12)
              << std::setprecision(2) << 1000.0 / fps << std::setw(14) << std::setprecision(1)
              << frames / cpu_s << std::setw(14) << std::setprecision(2) << tiles << std::setw(12)
              << std::setprecision(1) << setup_ms << "\n";
    results.push_back({{"case", c.name},
                       {"frames", frames},
                       {"frames_per_s", fps},
                       {"ms_per_frame", 1000.0 / fps},
                       {"cpu_frames_per_s", frames / cpu_s},
                       {"tiles_per_frame", tiles},
                       {"setup_ms", setup_ms},
                       {"checksum", checksum}});
  }
  if (!json_path.empty()) {
    std::ofstream out(json_path);
    out << nlohmann::json{{"benchmark", "simulator"}, {"threads", 1}, {"results", results}}.dump(2)
        << "\n";
  }
  return 0;
}
