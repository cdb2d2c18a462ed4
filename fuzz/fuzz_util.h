#pragma once
// Helpers shared by the libFuzzer targets: the parsers under test take paths, so each input is
// written to a file in a per-process scratch folder first.

#include <unistd.h>

#include <cstddef>
#include <cstdint>
#include <filesystem>
#include <fstream>
#include <string>

namespace irmosaic::fuzz {

// A scratch folder unique to this process (libFuzzer may run several jobs side by side).
inline const std::filesystem::path& ScratchDir() {
  static const std::filesystem::path dir = [] {
    std::filesystem::path p =
        std::filesystem::temp_directory_path() / ("irmosaic_fuzz_" + std::to_string(::getpid()));
    std::filesystem::create_directories(p);
    return p;
  }();
  return dir;
}

// Writes the fuzz input to `path` verbatim (binary, no newline translation).
inline void WriteBytes(const std::filesystem::path& path, const uint8_t* data, size_t size) {
  std::ofstream out(path, std::ios::binary | std::ios::trunc);
  out.write(reinterpret_cast<const char*>(data), static_cast<std::streamsize>(size));
}

}  // namespace irmosaic::fuzz
