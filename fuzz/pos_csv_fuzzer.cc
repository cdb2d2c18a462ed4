// libFuzzer target: PosTrack::LoadCsv on arbitrary bytes. Bad input must end in InputError;
// a track that loads must answer pose lookups without NaN.
#include <cmath>
#include <cstddef>
#include <cstdint>
#include <cstdlib>

#include "fuzz_util.h"
#include "irmosaic/error.h"
#include "irmosaic/pos.h"

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  const std::filesystem::path path = irmosaic::fuzz::ScratchDir() / "pos.csv";
  irmosaic::fuzz::WriteBytes(path, data, size);
  try {
    const irmosaic::PosTrack track = irmosaic::PosTrack::LoadCsv(path.string());
    const auto& records = track.records();
    const double t0 = records.front().time_s, t1 = records.back().time_s;
    for (double w : {0.0, 0.25, 0.5, 1.0}) {
      const irmosaic::PoseLookup lookup = track.At(t0 + w * (t1 - t0));
      if (lookup.status == irmosaic::PoseLookup::Status::kOk &&
          (!std::isfinite(lookup.pose.lat_deg) || !std::isfinite(lookup.pose.lon_deg) ||
           !std::isfinite(lookup.pose.height_m) ||
           !lookup.pose.ned_from_body.coeffs().allFinite())) {
        std::abort();  // A loaded track must never produce a non-finite pose.
      }
    }
  } catch (const irmosaic::InputError&) {
    // The expected outcome for bad input.
  }
  return 0;
}
