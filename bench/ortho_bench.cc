// Orthorectification cost per 640x512 16-bit and 8-bit frame on one core, and of the seam
// weights a render computes over the orthoimage (src/feather_weight.h: the scalar reference over
// whole rows, the SSE2 and AVX2 paths over each row's span).
// Usage: ortho_bench [--json FILE] [--frames N]
#include <time.h>

#include <chrono>
#include <cstdio>
#include <fstream>
#include <nlohmann/json.hpp>
#include <opencv2/core.hpp>
#include <string>

#include "../src/feather_weight.h"
#include "../src/simd_dispatch.h"
#include "../src/warp_bilinear.h"
#include "irmosaic/frame_geometry.h"
#include "irmosaic/orthorectify.h"

using namespace irmosaic;

// CPU time of this thread, ms: robust to other processes sharing the cores.
double ThreadCpuMs() {
  timespec t{};
  clock_gettime(CLOCK_THREAD_CPUTIME_ID, &t);
  return t.tv_sec * 1e3 + t.tv_nsec * 1e-6;
}

int main(int argc, char** argv) {
  std::string json_path;
  int frames = 400;
  for (int i = 1; i + 1 < argc; i += 2) {
    if (std::string(argv[i]) == "--json") json_path = argv[i + 1];
    if (std::string(argv[i]) == "--frames") frames = std::stoi(argv[i + 1]);
  }
  cv::setNumThreads(1);
  const CameraModel camera = DefaultInfraredCamera();
  cv::Mat frame16(camera.height, camera.width, CV_16U), frame8;
  cv::randu(frame16, 0, 65535);
  frame16.convertTo(frame8, CV_8U, 1.0 / 256.0);
  const LocalFrame local(47.2, 8.5);
  const double altitude_m = 1000.0;
  const MosaicGrid grid{altitude_m / camera.fx};  // Nadir GSD of the camera.
  nlohmann::json rows = nlohmann::json::array();
  std::printf("%-5s %-10s %-22s %-12s %-12s %-12s %-10s\n", "bits", "off_nadir", "warp", "ortho_px",
              "wall_ms", "cpu_ms", "target");
  // The warps: OpenCV's and the own one (exact_bilinear_16bit / _8bit), each over the whole box
  // (the registration's POS orthoimages) and over the footprint only (the renders).
  struct Variant {
    const char* name;
    bool footprint_only, own;
  };
  const Variant variants[] = {{"opencv box", false, false},
                              {"own box", false, true},
                              {"opencv footprint", true, false},
                              {"own footprint (render)", true, true}};
  for (const int bits : {16, 8}) {
    const cv::Mat& frame = bits == 16 ? frame16 : frame8;
    for (double off_nadir : {0.0, 30.0, 45.0}) {
      PosRecord r;
      r.lat_deg = 47.2;
      r.lon_deg = 8.5;
      r.height_m = altitude_m;
      r.gimbal_roll_deg = off_nadir;
      r.yaw_deg = 33.0;  // A rotated footprint, as on a flight.
      const FrameGeometry g =
          ComputeFrameGeometry(camera, PoseFromRecord(r), local, grid, FlatGround(0.0));
      double opencv_cpu_ms[2] = {0.0, 0.0};
      for (const Variant& v : variants) {
        OrthoOptions options;
        options.footprint_only = v.footprint_only;
        options.exact_bilinear_16bit = v.own;
        options.exact_bilinear_8bit = v.own;
        Orthorectifier worker(camera, options);
        worker.set_reuse_output(true);
        OrthoImage out;
        worker.Run(frame, g.mosaic_from_image, &out);  // Warm.
        const auto start = std::chrono::steady_clock::now();
        const double cpu_start = ThreadCpuMs();
        for (int i = 0; i < frames; ++i) worker.Run(frame, g.mosaic_from_image, &out);
        const double cpu_ms = (ThreadCpuMs() - cpu_start) / frames;
        const double ms =
            std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - start)
                .count() /
            frames;
        if (!v.own) opencv_cpu_ms[v.footprint_only] = cpu_ms;
        const double speedup = v.own ? opencv_cpu_ms[v.footprint_only] / cpu_ms : 1.0;
        std::printf("%-5d %-10.0f %-22s %-12s %-12.3f %-12.3f %-10s", bits, off_nadir, v.name,
                    (std::to_string(out.image.cols) + "x" + std::to_string(out.image.rows)).c_str(),
                    ms, cpu_ms, cpu_ms <= 2.0 ? "<= 2 ms" : "MISSED");
        if (v.own) std::printf(" %.2fx OpenCV's", speedup);
        std::printf("\n");
        rows.push_back({{"bits", bits},
                        {"off_nadir_deg", off_nadir},
                        {"warp", v.name},
                        {"footprint_only", v.footprint_only},
                        {"own_warp", v.own},
                        {"ortho_width", out.image.cols},
                        {"ortho_height", out.image.rows},
                        {"ms_per_frame", ms},
                        {"cpu_ms_per_frame", cpu_ms},
                        {"speedup_vs_opencv", speedup}});
      }
      if (simd::Avx2()) {
        // The own warp's two ways of reading pixel pairs (warp_bilinear.h: the gather
        // instruction or eight loads) over the same whole box, one after the other, 3 times.
        Orthorectifier worker(camera, OrthoOptions{});
        OrthoImage out;
        worker.Run(frame, g.mosaic_from_image, &out);
        cv::Matx33d src_from_dst;
        const Eigen::Matrix3d inverse = out.ortho_from_image.inverse();
        for (int i = 0; i < 3; ++i)
          for (int c = 0; c < 3; ++c) src_from_dst(i, c) = inverse(i, c);
        cv::Mat dst(out.image.size(), frame.type());
        double best[2] = {1e300, 1e300};
        for (int round = 0; round < 3; ++round) {
          for (const warp::GatherPath gather :
               {warp::GatherPath::kHardware, warp::GatherPath::kEmulated}) {
            const double cpu_start = ThreadCpuMs();
            for (int i = 0; i < frames; ++i)
              warp::WarpBilinearAvx2(frame, src_from_dst, &dst, gather);
            const int k = gather == warp::GatherPath::kEmulated;
            best[k] = std::min(best[k], (ThreadCpuMs() - cpu_start) / frames);
          }
        }
        for (const int k : {0, 1}) {
          const char* name = k ? "own box, 8 loads" : "own box, gather instr.";
          std::printf("%-5d %-10.0f %-22s %-12s %-12s %-12.3f %-10s %.2fx the gather instruction\n",
                      bits, off_nadir, name,
                      (std::to_string(dst.cols) + "x" + std::to_string(dst.rows)).c_str(), "-",
                      best[k], "", best[0] / best[k]);
          rows.push_back({{"bits", bits},
                          {"off_nadir_deg", off_nadir},
                          {"warp", name},
                          {"gather", k ? "emulated" : "hardware"},
                          {"ortho_width", dst.cols},
                          {"ortho_height", dst.rows},
                          {"cpu_ms_per_frame", best[k]},
                          {"speedup_vs_gather_instruction", best[0] / best[k]}});
        }
      }
      if (bits == 8) {
        // Seam weights of the render's orthoimage (the same for either bit depth).
        Orthorectifier worker(camera, [] {
          OrthoOptions o;
          o.footprint_only = true;
          return o;
        }());
        OrthoImage out;
        worker.Run(frame, g.mosaic_from_image, &out);
        std::array<Eigen::Vector2d, 4> quad;
        const std::array<Eigen::Vector2d, 4> corners = {
            Eigen::Vector2d(-0.5, -0.5), Eigen::Vector2d(camera.width - 0.5, -0.5),
            Eigen::Vector2d(camera.width - 0.5, camera.height - 0.5),
            Eigen::Vector2d(-0.5, camera.height - 0.5)};
        for (int k = 0; k < 4; ++k) {
          quad[k] = (out.ortho_from_image * corners[k].homogeneous()).hnormalized();
        }
        cv::Mat weight;
        double reference_cpu_ms = 0.0;
        for (const char* path :
             {"feather scalar rows", "feather SSE2 spans", "feather AVX2 spans"}) {
          const std::string name = path;
          const bool scalar = name == "feather scalar rows";
          const bool before = simd::SetAvx2Allowed(name == "feather AVX2 spans");
          if (name == "feather AVX2 spans" && !simd::Avx2()) {
            simd::SetAvx2Allowed(before);
            continue;
          }
          const double cpu_start = ThreadCpuMs();
          for (int i = 0; i < frames; ++i) {
            if (scalar) {
              feather::WeightScalar(quad, 24.0, out.mask, &weight);
            } else {
              feather::Weight(quad, 24.0, out.mask, &weight);
            }
          }
          const double cpu_ms = (ThreadCpuMs() - cpu_start) / frames;
          simd::SetAvx2Allowed(before);
          if (scalar) reference_cpu_ms = cpu_ms;
          std::printf("%-5s %-10.0f %-22s %-12s %-12s %-12.3f %-10s %.2fx the scalar rows\n", "-",
                      off_nadir, path,
                      (std::to_string(weight.cols) + "x" + std::to_string(weight.rows)).c_str(),
                      "-", cpu_ms, "", reference_cpu_ms / cpu_ms);
          rows.push_back({{"off_nadir_deg", off_nadir},
                          {"feather", name},
                          {"ortho_width", weight.cols},
                          {"ortho_height", weight.rows},
                          {"cpu_ms_per_frame", cpu_ms},
                          {"speedup_vs_scalar_rows", reference_cpu_ms / cpu_ms}});
        }
      }
    }
  }
  std::printf("the own warp's gather on this machine (measured at its first warp): %s\n",
              warp::GatherPathName());
  if (!json_path.empty()) {
    std::ofstream(json_path) << nlohmann::json{{"benchmark", "ortho"},
                                               {"threads", 1},
                                               {"warp_gather", warp::GatherPathName()},
                                               {"rows", rows}}
                                    .dump(2)
                             << "\n";
  }
  return 0;
}
