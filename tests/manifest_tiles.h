#pragma once
// Tests' own reading of a store manifest's tile lists (docs/store.md, "manifest.json"), written
// from the documented format rather than shared with the readers under test: format 1 lists
// tiles, format 2 blocks of 16 x 16 tiles with a bitmap of 64 hex digits (bit i, digit i / 4
// from its most significant bit, is tile (16 block_row + i / 16, 16 block_col + i % 16)).

#include <cstdint>
#include <nlohmann/json.hpp>
#include <set>
#include <string>
#include <utility>

namespace irmosaic::manifest_json {

using ManifestTile = std::pair<int64_t, int64_t>;  // (row, col)

// The tiles one `levels[]` entry lists, in either format.
inline std::set<ManifestTile> LevelTiles(const nlohmann::json& level) {
  std::set<ManifestTile> tiles;
  if (level.contains("tiles")) {
    for (const auto& t : level["tiles"]) tiles.insert({t[0].get<int64_t>(), t[1].get<int64_t>()});
  }
  if (level.contains("blocks")) {
    for (const auto& b : level["blocks"]) {
      const int64_t row0 = 16 * b[0].get<int64_t>(), col0 = 16 * b[1].get<int64_t>();
      const std::string hex = b[2].get<std::string>();
      for (int i = 0; i < 256; ++i) {
        const int digit = std::stoi(hex.substr(i / 4, 1), nullptr, 16);
        if (digit & (8 >> (i % 4))) tiles.insert({row0 + i / 16, col0 + i % 16});
      }
    }
  }
  return tiles;
}

// Tiles of every level together.
inline size_t TileCountAllLevels(const nlohmann::json& manifest) {
  size_t count = 0;
  for (const auto& level : manifest["levels"]) count += LevelTiles(level).size();
  return count;
}

// The same manifest as format 1 (what stores written before format 2 hold): each level's tiles
// listed as [row, col] in row-major order, as that writer listed them.
inline nlohmann::json AsFormat1(nlohmann::json manifest) {
  manifest["format_version"] = 1;
  for (auto& level : manifest["levels"]) {
    nlohmann::json tiles = nlohmann::json::array();
    for (const ManifestTile& t : LevelTiles(level)) tiles.push_back({t.first, t.second});
    level.erase("blocks");
    level["tiles"] = tiles;
  }
  return manifest;
}

}  // namespace irmosaic::manifest_json
