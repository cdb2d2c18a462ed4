// libFuzzer target: TileStore::OpenReadOnly on a store folder whose manifest.json is the fuzz
// input (no tiles, no frames.gpkg), then a small window read. Bad input must end in InputError
// (or another irmosaic::Error); never a crash, a hang or a huge allocation.
#include <cstddef>
#include <cstdint>
#include <memory>

#include "fuzz_util.h"
#include "irmosaic/error.h"
#include "irmosaic/tile_store.h"

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  const std::filesystem::path store = irmosaic::fuzz::ScratchDir() / "store";
  std::filesystem::create_directories(store);
  irmosaic::fuzz::WriteBytes(store / "manifest.json", data, size);
  try {
    std::unique_ptr<irmosaic::TileStore> reader = irmosaic::TileStore::OpenReadOnly(store.string());
    (void)reader->published_generation();
    (void)reader->application_state();
    (void)reader->FrameRecords();
    cv::Mat image, coverage;
    // Tiles the manifest names are absent on disk: the read must report that, not crash.
    reader->ReadWindow(cv::Rect(-3, -3, 8, 8), &image, &coverage);
  } catch (const irmosaic::Error&) {
    // The expected outcome for bad input (InputError) or missing tiles (OutputError).
  }
  return 0;
}
