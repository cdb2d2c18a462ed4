// libFuzzer target: CameraModel::LoadJson on arbitrary bytes. Bad input must end in InputError;
// a camera that loads must undistort its centre pixel to a finite point.
#include <cstddef>
#include <cstdint>
#include <cstdlib>

#include "fuzz_util.h"
#include "irmosaic/camera.h"
#include "irmosaic/error.h"

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  const std::filesystem::path path = irmosaic::fuzz::ScratchDir() / "camera.json";
  irmosaic::fuzz::WriteBytes(path, data, size);
  try {
    const irmosaic::CameraModel camera = irmosaic::CameraModel::LoadJson(path.string());
    const Eigen::Vector2d centre = camera.Undistort({camera.cx, camera.cy});
    if (!centre.allFinite()) std::abort();  // A validated camera must map its centre.
  } catch (const irmosaic::InputError&) {
    // The expected outcome for bad input.
  }
  return 0;
}
