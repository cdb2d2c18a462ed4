// The IRMOSAIC GDAL driver: the live irmosaic store (docs/store.md) as one read-only raster.
//
// Design: the driver reads manifest.json itself and serves blocks straight from the tile
// GeoTIFFs (opened through GDAL's GTiff driver only). It does not open the store's mosaic.vrt:
// a VRT can name any file, while tile paths built here from validated integer indices, and
// checked against the store folder after resolving symlinks, cannot leave the store.
#include "irmosaic_driver.h"

#include <algorithm>
#include <bit>
#include <climits>
#include <cmath>
#include <cstdint>
#include <cstdlib>
#include <cstring>
#include <exception>
#include <memory>
#include <nlohmann/json.hpp>
#include <set>
#include <string>
#include <utility>
#include <vector>

#include "cpl_conv.h"
#include "cpl_error.h"
#include "cpl_string.h"
#include "cpl_vsi.h"
#include "gdal_priv.h"
#include "ogr_spatialref.h"

namespace irmosaic {
namespace {

constexpr const char* kDriverName = "IRMOSAIC";
constexpr const char* kFormatName = "irmosaic-store";
// 2 lists a level's tiles as blocks with a presence bitmap; 1 listed every tile. Both are read.
constexpr int kFormatVersion = 2;
// Bounds that keep a hostile manifest from costing unbounded memory or time.
constexpr int64_t kMaxManifestBytes = 256LL << 20;  // ~10 M tile entries.
constexpr int kMaxJsonDepth = 64;
constexpr int kMaxLevels = 24;
constexpr size_t kMaxTilesTotal = 8u << 20;
constexpr int64_t kMaxTileIndex = 1 << 20;  // |row|, |col| of a level-0 tile.
// Format 2: a block is kBlockTiles x kBlockTiles tiles (the store's VRT blocks), its bitmap 64
// hex digits; block indices stay within [-2^16, 2^16) so that its tiles are within the above.
constexpr int64_t kBlockTiles = 16;
constexpr int64_t kMaxBlockIndex = kMaxTileIndex / kBlockTiles;
constexpr int kMinTileSize = 16, kMaxTileSize = 8192;
constexpr size_t kMaxWktBytes = 1 << 16;

using TileIndex = std::pair<int64_t, int64_t>;  // (row, col)

// What the driver needs from a manifest, validated.
struct StoreIndex {
  std::string root;  // Store folder, symlinks resolved; every tile must lie under it.
  int format_version = 0;
  int64_t generation = 0;
  std::string published_utc;
  std::string crs_wkt;
  double origin_lat_deg = 0.0, origin_lon_deg = 0.0;
  double gsd_m = 0.0;
  int tile_size = 0;
  GDALDataType type = GDT_Unknown;
  double alpha_max = 0.0;
  int64_t frame_count = 0;
  double time_min_s = 0.0, time_max_s = 0.0;
  std::vector<std::set<TileIndex>> levels;         // Level 0 first; tiles present.
  int64_t row0 = 0, col0 = 0, row1 = 0, col1 = 0;  // Level-0 tile bounds (half-open).
  // The extent served: the tile bounds grown to the planned_bounds_px of the manifest (the
  // flight's extent foreseen from its POS) when it has them, in level-0 tiles (half-open).
  int64_t extent_row0 = 0, extent_col0 = 0, extent_row1 = 0, extent_col1 = 0;
  int usable_levels = 1;  // Levels with an exact pixel grid (tile_size divisible by 2^l).
};

// The tile list the reads use, shared by a level-0 dataset and its overviews. A client that keeps
// the dataset open (QGIS keeps its GDAL handle for the layer's life) sees the store grow: before
// each read of the data band the manifest is checked (one stat) and, once it has been replaced,
// read again (open option LIVE=NO turns this off). Only the tile list and the metadata follow;
// the raster's size and georeferencing stay those of the open, so tiles beyond the opened extent
// show after a reopen (the manifest's planned_bounds_px, when the writer knew the flight ahead,
// makes the opened extent the whole flight's).
struct LiveIndex {
  std::string manifest_path;
  bool live = true;
  // The manifest as last read: inode, size, modification time (ns). The store replaces it by
  // rename, so a new publish is a new file.
  int64_t inode = -1, size = -1, mtime_ns = -1;
  std::shared_ptr<const StoreIndex> index;
  int64_t refreshes = 0;  // Newer generations taken since the open.

  // Stats the manifest; true if it is another file than the one last read (and remembers it).
  bool Replaced() {
    VSIStatBufL stat;
    if (VSIStatL(manifest_path.c_str(), &stat) != 0) return false;
#ifdef __linux__
    const int64_t ns =
        static_cast<int64_t>(stat.st_mtim.tv_sec) * 1000000000 + stat.st_mtim.tv_nsec;
#else
    const int64_t ns = static_cast<int64_t>(stat.st_mtime) * 1000000000;
#endif
    if (static_cast<int64_t>(stat.st_ino) == inode && static_cast<int64_t>(stat.st_size) == size &&
        ns == mtime_ns) {
      return false;
    }
    inode = static_cast<int64_t>(stat.st_ino);
    size = static_cast<int64_t>(stat.st_size);
    mtime_ns = ns;
    return true;
  }
};

// Largest nesting of arrays/objects in JSON text (strings skipped), so a deeply nested document
// is refused before the parser recurses or allocates for it.
int JsonDepth(const char* text, size_t size) {
  int depth = 0, max_depth = 0;
  bool in_string = false;
  for (size_t i = 0; i < size; ++i) {
    const char c = text[i];
    if (in_string) {
      if (c == '\\')
        ++i;
      else if (c == '"')
        in_string = false;
      continue;
    }
    if (c == '"')
      in_string = true;
    else if (c == '[' || c == '{')
      max_depth = std::max(max_depth, ++depth);
    else if (c == ']' || c == '}')
      --depth;
    if (max_depth > kMaxJsonDepth) break;
  }
  return max_depth;
}

// Field readers: each refuses a missing field or a wrong type/range with *error set.
const nlohmann::json* Field(const nlohmann::json& j, const char* key, std::string* error) {
  const auto it = j.find(key);
  if (it == j.end()) {
    *error = std::string("field \"") + key + "\" is missing";
    return nullptr;
  }
  return &*it;
}

bool GetInt(const nlohmann::json& j, const char* key, int64_t lo, int64_t hi, int64_t* out,
            std::string* error) {
  const nlohmann::json* f = Field(j, key, error);
  if (f == nullptr) return false;
  if (!f->is_number_integer()) {
    *error = std::string("field \"") + key + "\" must be an integer";
    return false;
  }
  // A huge unsigned value does not fit int64: compare as unsigned first.
  if (f->is_number_unsigned() && f->get<uint64_t>() > static_cast<uint64_t>(INT64_MAX)) {
    *error = std::string("field \"") + key + "\" is out of range";
    return false;
  }
  const int64_t v = f->get<int64_t>();
  if (v < lo || v > hi) {
    *error = std::string("field \"") + key + "\" = " + std::to_string(v) + " is outside [" +
             std::to_string(lo) + ", " + std::to_string(hi) + "]";
    return false;
  }
  *out = v;
  return true;
}

bool GetDouble(const nlohmann::json& j, const char* key, double lo, double hi, double* out,
               std::string* error) {
  const nlohmann::json* f = Field(j, key, error);
  if (f == nullptr) return false;
  if (!f->is_number()) {
    *error = std::string("field \"") + key + "\" must be a number";
    return false;
  }
  const double v = f->get<double>();
  if (!std::isfinite(v) || v < lo || v > hi) {
    *error = std::string("field \"") + key + "\" is not a finite number in range";
    return false;
  }
  *out = v;
  return true;
}

bool GetString(const nlohmann::json& j, const char* key, size_t max_bytes, std::string* out,
               std::string* error) {
  const nlohmann::json* f = Field(j, key, error);
  if (f == nullptr) return false;
  if (!f->is_string()) {
    *error = std::string("field \"") + key + "\" must be a string";
    return false;
  }
  *out = f->get<std::string>();
  if (out->size() > max_bytes) {
    *error = std::string("field \"") + key + "\" is too long";
    return false;
  }
  return true;
}

bool ValidWkt(const std::string& wkt, std::string* error) {
  OGRSpatialReference srs;
  if (srs.importFromWkt(wkt.c_str()) != OGRERR_NONE) {
    *error = "field \"crs_wkt\" is not a valid WKT CRS";
    return false;
  }
  return true;
}

// A JSON integer within [lo, hi] (a huge unsigned value does not fit int64: checked first).
bool IntegerIn(const nlohmann::json& v, int64_t lo, int64_t hi, int64_t* out) {
  if (!v.is_number_integer()) return false;
  if (v.is_number_unsigned() && v.get<uint64_t>() > static_cast<uint64_t>(hi)) return false;
  *out = v.get<int64_t>();
  return *out >= lo && *out <= hi;
}

// Whether `level` holds the list of the other format, or both: refused rather than half read.
bool OneTileList(const nlohmann::json& level, size_t l, const char* key, std::string* error) {
  const std::string where = "levels[" + std::to_string(l) + "]";
  if (level.contains("tiles") && level.contains("blocks")) {
    *error = where + " holds both \"tiles\" (format 1) and \"blocks\" (format 2)";
    return false;
  }
  if (!level.contains(key)) {
    *error = where + "." + key + " is missing (this manifest's format_version lists a level's " +
             "tiles as \"" + key + "\")";
    return false;
  }
  if (!level[key].is_array()) {
    *error = where + "." + key + " must be an array";
    return false;
  }
  return true;
}

bool CountTiles(size_t added, size_t* tiles_total, std::string* error) {
  *tiles_total += added;
  if (*tiles_total > kMaxTilesTotal) {
    *error = "manifest lists more than " + std::to_string(kMaxTilesTotal) + " tiles";
    return false;
  }
  return true;
}

// Format 1: "tiles": [[row, col], ...].
bool ParseTiles(const nlohmann::json& level, size_t l, std::set<TileIndex>* out,
                size_t* tiles_total, std::string* error) {
  if (!OneTileList(level, l, "tiles", error)) return false;
  const nlohmann::json& tiles = level["tiles"];
  if (!CountTiles(tiles.size(), tiles_total, error)) return false;
  for (const nlohmann::json& t : tiles) {
    if (!t.is_array() || t.size() != 2 || !t[0].is_number_integer() || !t[1].is_number_integer()) {
      *error = "levels[" + std::to_string(l) + "].tiles holds an entry that is not [row, col]";
      return false;
    }
    int64_t row = 0, col = 0;
    if (!IntegerIn(t[0], -kMaxTileIndex, kMaxTileIndex, &row) ||
        !IntegerIn(t[1], -kMaxTileIndex, kMaxTileIndex, &col)) {
      *error = "levels[" + std::to_string(l) + "].tiles holds an index beyond +-" +
               std::to_string(kMaxTileIndex);
      return false;
    }
    out->insert({row, col});
  }
  return true;
}

int HexDigitValue(char c) {
  if (c >= '0' && c <= '9') return c - '0';
  if (c >= 'a' && c <= 'f') return c - 'a' + 10;
  return -1;
}

// Format 2: "blocks": [[block_row, block_col, "<64 hex digits>"], ...]; bit i of the bitmap
// (digit i / 4, from its most significant bit) is tile (16 block_row + i / 16,
// 16 block_col + i % 16). Each block once, each with at least one tile (docs/store.md).
bool ParseBlocks(const nlohmann::json& level, size_t l, std::set<TileIndex>* out,
                 size_t* tiles_total, std::string* error) {
  if (!OneTileList(level, l, "blocks", error)) return false;
  const nlohmann::json& blocks = level["blocks"];
  // Every entry is checked and its tiles counted before any is held (~70 bytes of text name up
  // to 256 tiles); then the tiles are inserted.
  std::set<TileIndex> seen;
  std::vector<TileIndex> first_tiles;
  for (size_t k = 0; k < blocks.size(); ++k) {
    const nlohmann::json& b = blocks[k];
    const std::string where = "levels[" + std::to_string(l) + "].blocks[" + std::to_string(k) + "]";
    if (!b.is_array() || b.size() != 3 || !b[0].is_number_integer() || !b[1].is_number_integer() ||
        !b[2].is_string()) {
      *error = where + " is not [block_row, block_col, \"<64 hex digits>\"]";
      return false;
    }
    int64_t block_row = 0, block_col = 0;
    if (!IntegerIn(b[0], -kMaxBlockIndex, kMaxBlockIndex - 1, &block_row) ||
        !IntegerIn(b[1], -kMaxBlockIndex, kMaxBlockIndex - 1, &block_col)) {
      *error = where + " has a block index beyond [-" + std::to_string(kMaxBlockIndex) + ", " +
               std::to_string(kMaxBlockIndex) + ")";
      return false;
    }
    const std::string& hex = b[2].get_ref<const std::string&>();
    if (hex.size() != 4 * kBlockTiles ||
        !std::all_of(hex.begin(), hex.end(), [](char c) { return HexDigitValue(c) >= 0; })) {
      *error = where + " has a bitmap that is not 64 lowercase hex digits";
      return false;
    }
    if (hex.find_first_not_of('0') == std::string::npos) {
      *error = where + " has a bitmap of no tile (a block is listed only if it holds one)";
      return false;
    }
    if (!seen.insert({block_row, block_col}).second) {
      *error = where + " lists block [" + std::to_string(block_row) + ", " +
               std::to_string(block_col) + "] a second time";
      return false;
    }
    size_t count = 0;
    for (const char c : hex) count += std::popcount(static_cast<unsigned>(HexDigitValue(c)));
    if (!CountTiles(count, tiles_total, error)) return false;
    first_tiles.push_back({block_row * kBlockTiles, block_col * kBlockTiles});
  }
  for (size_t k = 0; k < blocks.size(); ++k) {
    const std::string& hex = blocks[k][2].get_ref<const std::string&>();
    for (size_t digit = 0; digit < hex.size(); ++digit) {
      const int value = HexDigitValue(hex[digit]);
      for (int bit = 0; bit < 4; ++bit) {
        if ((value & (8 >> bit)) == 0) continue;
        const int64_t i = static_cast<int64_t>(4 * digit) + bit;
        out->insert(
            {first_tiles[k].first + i / kBlockTiles, first_tiles[k].second + i % kBlockTiles});
      }
    }
  }
  return true;
}

// Validates manifest text into *index (all but `root`). Returns false with *error on refusal,
// and sets *not_a_store when the JSON is valid but is some other format (then Open stays quiet).
// A store with no level-0 tile yet is refused unless `allow_empty` (its footprints layer alone
// is then of use; index->levels[0] stays empty).
bool ParseManifest(const char* text, size_t size, StoreIndex* index, std::string* error,
                   bool* not_a_store, bool allow_empty = false) {
  *not_a_store = false;
  if (JsonDepth(text, size) > kMaxJsonDepth) {
    *error = "manifest nests deeper than " + std::to_string(kMaxJsonDepth) + " levels";
    return false;
  }
  const nlohmann::json j = nlohmann::json::parse(text, text + size, nullptr, false);
  if (j.is_discarded()) {
    *error = "manifest is not valid JSON (truncated or corrupt)";
    return false;
  }
  if (!j.is_object()) {
    *error = "manifest is not a JSON object";
    return false;
  }
  std::string format;
  if (!GetString(j, "format", 64, &format, error)) return false;
  if (format != kFormatName) {
    *not_a_store = true;
    *error = "manifest format is \"" + format + "\", not \"" + kFormatName + "\"";
    return false;
  }
  int64_t v = 0;
  if (!GetInt(j, "format_version", 1, INT32_MAX, &v, error)) return false;
  if (v > kFormatVersion) {
    *error = "manifest format_version " + std::to_string(v) + " is newer than this driver's (" +
             std::to_string(kFormatVersion) + "); update the IRMOSAIC plug-in";
    return false;
  }
  index->format_version = static_cast<int>(v);
  if (!GetInt(j, "generation", 0, INT64_MAX, &index->generation, error)) return false;
  if (j.contains("published_utc") && j["published_utc"].is_string()) {
    index->published_utc = j["published_utc"].get<std::string>().substr(0, 64);
  }
  if (!GetString(j, "crs_wkt", kMaxWktBytes, &index->crs_wkt, error)) return false;
  const nlohmann::json* origin = Field(j, "origin", error);
  if (origin == nullptr) return false;
  if (!origin->is_object()) {
    *error = "field \"origin\" must be an object";
    return false;
  }
  if (!GetDouble(*origin, "lat_deg", -90, 90, &index->origin_lat_deg, error) ||
      !GetDouble(*origin, "lon_deg", -180, 180, &index->origin_lon_deg, error)) {
    return false;
  }
  if (!GetDouble(j, "gsd_m", 1e-6, 1e6, &index->gsd_m, error)) return false;
  if (index->gsd_m <= 0.0) {
    *error = "field \"gsd_m\" must be positive";
    return false;
  }
  if (!GetInt(j, "tile_size", kMinTileSize, kMaxTileSize, &v, error)) return false;
  if (v % 16 != 0) {
    *error = "field \"tile_size\" must be a multiple of 16";
    return false;
  }
  index->tile_size = static_cast<int>(v);
  std::string type_name;
  if (!GetString(j, "data_type", 16, &type_name, error)) return false;
  if (type_name == "Byte")
    index->type = GDT_Byte;
  else if (type_name == "UInt16")
    index->type = GDT_UInt16;
  else if (type_name == "Float32")
    index->type = GDT_Float32;
  else {
    *error = "field \"data_type\" = \"" + type_name + "\" is not Byte, UInt16 or Float32";
    return false;
  }
  index->alpha_max = index->type == GDT_UInt16 ? 65535.0 : 255.0;
  if (j.contains("alpha_max") && !GetDouble(j, "alpha_max", 1, 65535, &index->alpha_max, error)) {
    return false;
  }
  // Frames: optional for the raster, but typed when present.
  if (j.contains("frames") && !j["frames"].is_null()) {
    const nlohmann::json& frames = j["frames"];
    if (!frames.is_object()) {
      *error = "field \"frames\" must be an object";
      return false;
    }
    if (!GetInt(frames, "count", 0, INT64_MAX, &index->frame_count, error)) return false;
    // The time range is null (NaN written by JSON) while there are no frames.
    for (const auto& [key, out] : {std::pair{"time_min_s", &index->time_min_s},
                                   std::pair{"time_max_s", &index->time_max_s}}) {
      if (frames.contains(key) && !frames[key].is_null() &&
          !GetDouble(frames, key, -1e12, 1e12, out, error)) {
        return false;
      }
    }
  }

  const nlohmann::json* levels = Field(j, "levels", error);
  if (levels == nullptr) return false;
  if (!levels->is_array() || levels->empty() || levels->size() > kMaxLevels) {
    *error = "field \"levels\" must be an array of 1 to " + std::to_string(kMaxLevels) + " levels";
    return false;
  }
  size_t tiles_total = 0;
  index->levels.assign(levels->size(), {});
  for (size_t l = 0; l < levels->size(); ++l) {
    const nlohmann::json& level = (*levels)[l];
    if (!level.is_object()) {
      *error = "levels[" + std::to_string(l) + "] must be an object";
      return false;
    }
    int64_t level_number = 0;
    if (!GetInt(level, "level", 0, kMaxLevels, &level_number, error)) return false;
    if (level_number != static_cast<int64_t>(l)) {
      *error = "levels[" + std::to_string(l) + "] has level " + std::to_string(level_number);
      return false;
    }
    // Tiles are always read from tiles/<l>/<row>_<col>.tif; any other pattern (e.g. one
    // pointing out of the store) is refused rather than followed.
    if (level.contains("path_pattern")) {
      const std::string expected = "tiles/" + std::to_string(l) + "/{row}_{col}.tif";
      if (!level["path_pattern"].is_string() ||
          level["path_pattern"].get<std::string>() != expected) {
        *error = "levels[" + std::to_string(l) + "].path_pattern must be \"" + expected + "\"";
        return false;
      }
    }
    const bool ok = index->format_version >= 2
                        ? ParseBlocks(level, l, &index->levels[l], &tiles_total, error)
                        : ParseTiles(level, l, &index->levels[l], &tiles_total, error);
    if (!ok) return false;
  }
  if (index->levels[0].empty()) {
    if (!allow_empty) {
      *error = "the store holds no tiles yet (nothing published)";
      return false;
    }
    return ValidWkt(index->crs_wkt, error);
  }
  index->row0 = index->col0 = INT64_MAX;
  index->row1 = index->col1 = INT64_MIN;
  for (const TileIndex& t : index->levels[0]) {
    index->row0 = std::min(index->row0, t.first);
    index->col0 = std::min(index->col0, t.second);
    index->row1 = std::max(index->row1, t.first + 1);
    index->col1 = std::max(index->col1, t.second + 1);
  }
  const int64_t width = (index->col1 - index->col0) * index->tile_size;
  const int64_t height = (index->row1 - index->row0) * index->tile_size;
  if (width > INT_MAX || height > INT_MAX) {
    *error = "the mosaic is " + std::to_string(width) + " x " + std::to_string(height) +
             " pixels, beyond GDAL's raster size";
    return false;
  }
  // The published bounds must agree with the tiles (a torn or edited manifest does not).
  if (j.contains("bounds_px") && !j["bounds_px"].is_null()) {
    const nlohmann::json& b = j["bounds_px"];
    // TileStore writes these integral values as JSON reals (e.g. -512.0): read numbers.
    double c0 = 0, r0 = 0, c1 = 0, r1 = 0;
    if (!b.is_object()) {
      *error = "field \"bounds_px\" must be an object";
      return false;
    }
    if (!GetDouble(b, "col_min", -1e15, 1e15, &c0, error) ||
        !GetDouble(b, "row_min", -1e15, 1e15, &r0, error) ||
        !GetDouble(b, "col_max", -1e15, 1e15, &c1, error) ||
        !GetDouble(b, "row_max", -1e15, 1e15, &r1, error)) {
      return false;
    }
    const double t = index->tile_size;
    if (c0 != static_cast<double>(index->col0) * t || r0 != static_cast<double>(index->row0) * t ||
        c1 != static_cast<double>(index->col1) * t || r1 != static_cast<double>(index->row1) * t) {
      *error = "bounds_px disagrees with the level-0 tiles listed";
      return false;
    }
  }
  index->extent_row0 = index->row0;
  index->extent_col0 = index->col0;
  index->extent_row1 = index->row1;
  index->extent_col1 = index->col1;
  // The planned extent: optional, a display hint only (nothing outside it is refused).
  if (j.contains("planned_bounds_px") && !j["planned_bounds_px"].is_null()) {
    const nlohmann::json& b = j["planned_bounds_px"];
    double c0 = 0, r0 = 0, c1 = 0, r1 = 0;
    const double limit = static_cast<double>(kMaxTileIndex) * index->tile_size;
    if (!b.is_object()) {
      *error = "field \"planned_bounds_px\" must be an object";
      return false;
    }
    if (!GetDouble(b, "col_min", -limit, limit, &c0, error) ||
        !GetDouble(b, "row_min", -limit, limit, &r0, error) ||
        !GetDouble(b, "col_max", -limit, limit, &c1, error) ||
        !GetDouble(b, "row_max", -limit, limit, &r1, error)) {
      *error = "planned_bounds_px: " + *error;
      return false;
    }
    if (!(c0 < c1 && r0 < r1)) {
      *error = "planned_bounds_px is empty (col_min >= col_max or row_min >= row_max)";
      return false;
    }
    const double t = index->tile_size;
    index->extent_col0 = std::min(index->col0, static_cast<int64_t>(std::floor(c0 / t)));
    index->extent_row0 = std::min(index->row0, static_cast<int64_t>(std::floor(r0 / t)));
    index->extent_col1 = std::max(index->col1, static_cast<int64_t>(std::ceil(c1 / t)));
    index->extent_row1 = std::max(index->row1, static_cast<int64_t>(std::ceil(r1 / t)));
    const int64_t w = (index->extent_col1 - index->extent_col0) * index->tile_size;
    const int64_t h = (index->extent_row1 - index->extent_row0) * index->tile_size;
    if (w > INT_MAX || h > INT_MAX) {
      *error = "planned_bounds_px make the mosaic " + std::to_string(w) + " x " +
               std::to_string(h) + " pixels, beyond GDAL's raster size";
      return false;
    }
  }
  index->usable_levels = 1;
  while (index->usable_levels < static_cast<int>(index->levels.size()) &&
         index->tile_size % (1 << index->usable_levels) == 0) {
    ++index->usable_levels;
  }
  return ValidWkt(index->crs_wkt, error);
}

// Reads a whole file of at most kMaxManifestBytes through VSI.
bool ReadSmallFile(const std::string& path, std::string* out, std::string* error) {
  VSIStatBufL stat;
  if (VSIStatL(path.c_str(), &stat) != 0 || !VSI_ISREG(stat.st_mode)) {
    *error = "cannot find " + path;
    return false;
  }
  if (stat.st_size > kMaxManifestBytes) {
    *error = path + " is larger than " + std::to_string(kMaxManifestBytes >> 20) + " MiB";
    return false;
  }
  VSILFILE* f = VSIFOpenL(path.c_str(), "rb");
  if (f == nullptr) {
    *error = "cannot open " + path;
    return false;
  }
  out->resize(static_cast<size_t>(stat.st_size));
  const size_t got = out->empty() ? 0 : VSIFReadL(out->data(), 1, out->size(), f);
  VSIFCloseL(f);
  out->resize(got);
  return true;
}

// Resolved absolute path, or "" if it does not exist.
std::string RealPath(const std::string& path) {
  char* resolved = realpath(path.c_str(), nullptr);
  if (resolved == nullptr) return {};
  std::string result(resolved);
  free(resolved);
  return result;
}

// Where the manifest is for a store folder or manifest path, and whether the name fits.
std::string ManifestPathOf(const GDALOpenInfo* info) {
  if (info->bIsDirectory) return CPLFormFilename(info->pszFilename, "manifest.json", nullptr);
  return info->pszFilename;
}

// Whether the first bytes of a manifest look like an irmosaic store's: a JSON object whose head
// names "irmosaic-store" (TileStore writes "format" as the first key), or whose first key is
// "alpha_max" (earlier writers sorted the keys, so "format" came after the WKT and the
// application state, beyond any cheap header; Open checks the format of those and stays quiet
// for other JSON).
bool LooksLikeManifest(const char* head, size_t size) {
  const std::string text(head, strnlen(head, size));
  size_t i = text.find_first_not_of(" \t\r\n");
  if (i == std::string::npos || text[i] != '{') return false;
  if (text.find("\"irmosaic-store\"") != std::string::npos) return true;
  i = text.find_first_not_of(" \t\r\n", i + 1);
  // Nothing after "{": a truncated file; claim it so that Open says so.
  if (i == std::string::npos) return size < 1024;
  return text.compare(i, 11, "\"alpha_max\"") == 0;
}

int Identify(GDALOpenInfo* info) {
  constexpr size_t kHeadBytes = 1024;  // What GDAL reads of a file's header by default.
  if (info->bIsDirectory) {
    // Cheap: one open and the first bytes of the manifest.
    const std::string manifest = ManifestPathOf(info);
    VSILFILE* f = VSIFOpenL(manifest.c_str(), "rb");
    if (f == nullptr) return FALSE;
    std::vector<char> head(kHeadBytes);
    const size_t got = VSIFReadL(head.data(), 1, head.size(), f);
    VSIFCloseL(f);
    return LooksLikeManifest(head.data(), got) ? TRUE : FALSE;
  }
  if (!EQUAL(CPLGetFilename(info->pszFilename), "manifest.json") || info->nHeaderBytes < 2) {
    return FALSE;
  }
  return LooksLikeManifest(reinterpret_cast<const char*>(info->pabyHeader),
                           static_cast<size_t>(info->nHeaderBytes))
             ? TRUE
             : FALSE;
}

class IrmosaicDataset;

// A band of one level: band 1 the data, band 2 the alpha (coverage).
class IrmosaicBand final : public GDALRasterBand {
 public:
  IrmosaicBand(IrmosaicDataset* dataset, int band);
  CPLErr IReadBlock(int block_x, int block_y, void* data) override;
  // A read of the data band first takes a newer published generation (IrmosaicDataset::Refresh).
  // Refreshing on band 1 only keeps a render consistent: its alpha, read after the data, comes
  // from the same tiles; read before, it may lag one generation (new pixels transparent once).
  CPLErr IRasterIO(GDALRWFlag rw, int x, int y, int w, int h, void* data, int buf_w, int buf_h,
                   GDALDataType buf_type, GSpacing pixel_space, GSpacing line_space,
                   GDALRasterIOExtraArg* extra) override;
  GDALColorInterp GetColorInterpretation() override {
    return nBand == 1 ? GCI_GrayIndex : GCI_AlphaBand;
  }
  int GetOverviewCount() override;
  GDALRasterBand* GetOverview(int i) override;
};

// One level of the store as a dataset; level 0 owns the overview levels and, when asked for,
// the footprints layer. Without `with_raster` (a vector-only open) it has no bands.
class IrmosaicDataset final : public GDALDataset {
 public:
  // `root` is the level-0 dataset (nullptr: this one), which the overviews share `live` with.
  IrmosaicDataset(std::shared_ptr<LiveIndex> live, int level, bool with_raster = true,
                  IrmosaicDataset* root = nullptr)
      : index_(live->index), live_(std::move(live)), root_(root != nullptr ? root : this) {
    level_ = level;
    eAccess = GA_ReadOnly;
    srs_.importFromWkt(index_->crs_wkt.c_str());
    srs_.SetAxisMappingStrategy(OAMS_TRADITIONAL_GIS_ORDER);
    if (!with_raster || index_->levels[0].empty()) return;
    const int64_t t_level = index_->tile_size >> level;  // Level-0 tile side at this level.
    col_offset_px_ = index_->extent_col0 * t_level;
    row_offset_px_ = index_->extent_row0 * t_level;
    nRasterXSize = static_cast<int>((index_->extent_col1 - index_->extent_col0) * t_level);
    nRasterYSize = static_cast<int>((index_->extent_row1 - index_->extent_row0) * t_level);
    for (int b = 1; b <= 2; ++b) SetBand(b, new IrmosaicBand(this, b));
    if (level == 0) {
      for (int l = 1; l < index_->usable_levels; ++l) {
        overviews_.push_back(std::make_unique<IrmosaicDataset>(live_, l, true, this));
      }
    }
  }

  // Sets the metadata items from the index (at the open and after a refresh).
  void SetIndexMetadata(const StoreIndex& index) {
    const auto set = [&](const char* key, const std::string& value) {
      SetMetadataItem(key, value.c_str());
    };
    set("IRMOSAIC_FORMAT_VERSION", std::to_string(index.format_version));
    set("IRMOSAIC_GENERATION", std::to_string(index.generation));
    set("IRMOSAIC_PUBLISHED_UTC", index.published_utc);
    set("IRMOSAIC_FRAME_COUNT", std::to_string(index.frame_count));
    set("IRMOSAIC_TIME_MIN_S", CPLSPrintf("%.6f", index.time_min_s));
    set("IRMOSAIC_TIME_MAX_S", CPLSPrintf("%.6f", index.time_max_s));
    set("IRMOSAIC_GSD_M", CPLSPrintf("%.9g", index.gsd_m));
    set("IRMOSAIC_ORIGIN_LAT_DEG", CPLSPrintf("%.10f", index.origin_lat_deg));
    set("IRMOSAIC_ORIGIN_LON_DEG", CPLSPrintf("%.10f", index.origin_lon_deg));
    set("IRMOSAIC_TILE_SIZE", std::to_string(index.tile_size));
    set("IRMOSAIC_LEVELS", std::to_string(index.usable_levels));
    set("IRMOSAIC_ALPHA_MAX", CPLSPrintf("%.0f", index.alpha_max));
    set("IRMOSAIC_FRAMES", index.root + "/frames.gpkg");
    set("IRMOSAIC_LIVE", live_->live ? "YES" : "NO");
  }

  // Takes a newer published generation of the store, if the manifest was replaced since it was
  // last read and the new one describes the same grid; then drops every cached block of every
  // level. A manifest that cannot be read or parsed now (a store being deleted) is skipped:
  // the reads go on with the tiles known. Called on the level-0 dataset.
  void Refresh() {
    LiveIndex& live = *live_;
    if (!live.live || !live.Replaced()) return;
    std::string text, error;
    auto index = std::make_shared<StoreIndex>();
    index->root = live.index->root;
    bool not_a_store = false;
    if (!ReadSmallFile(live.manifest_path, &text, &error) ||
        !ParseManifest(text.data(), text.size(), index.get(), &error, &not_a_store,
                       /*allow_empty=*/true)) {
      CPLDebug("IRMOSAIC", "refresh of %s skipped: %s", live.manifest_path.c_str(), error.c_str());
      return;
    }
    const StoreIndex& old = *live.index;
    if (index->generation == old.generation) return;
    if (index->tile_size != old.tile_size || index->type != old.type || index->gsd_m != old.gsd_m ||
        index->crs_wkt != old.crs_wkt) {
      CPLDebug("IRMOSAIC", "refresh of %s skipped: the store now has another grid",
               live.manifest_path.c_str());
      return;
    }
    live.index = std::move(index);
    ++live.refreshes;
    SetIndexMetadata(*live.index);
    for (int b = 1; b <= nBands; ++b) GetRasterBand(b)->FlushCache(false);
    for (auto& overview : overviews_) {
      for (int b = 1; b <= overview->nBands; ++b) overview->GetRasterBand(b)->FlushCache(false);
    }
  }

  CPLErr GetGeoTransform(double* gt) override {
    if (nBands == 0) return CE_Failure;
    const double scale = std::ldexp(1.0, level_);
    gt[0] = (static_cast<double>(index_->extent_col0) * index_->tile_size - 0.5) * index_->gsd_m;
    gt[1] = index_->gsd_m * scale;
    gt[2] = 0.0;
    gt[3] = -(static_cast<double>(index_->extent_row0) * index_->tile_size - 0.5) * index_->gsd_m;
    gt[4] = 0.0;
    gt[5] = -index_->gsd_m * scale;
    return CE_None;
  }
  const OGRSpatialReference* GetSpatialRef() const override {
    return nBands == 0 ? nullptr : &srs_;
  }

  // The footprints: layer "frames" of the store's frames.gpkg, served by GDAL's GPKG driver.
  int GetLayerCount() override { return frames_layer_ != nullptr ? 1 : 0; }
  OGRLayer* GetLayer(int i) override { return i == 0 ? frames_layer_ : nullptr; }

  // Opens frames.gpkg read-only (GPKG driver only, inside the store after resolving symlinks)
  // and keeps its layer "frames"; false with *error if there is none to serve.
  bool OpenFrames(std::string* error) {
    const std::string path = index_->root + "/frames.gpkg";
    const std::string real = RealPath(path);
    if (real.empty() || real.compare(0, index_->root.size() + 1, index_->root + "/") != 0) {
      *error = "frames.gpkg is missing or lies outside the store";
      return false;
    }
    const char* const allowed[] = {"GPKG", nullptr};
    frames_.reset(GDALDataset::Open(real.c_str(), GDAL_OF_VECTOR | GDAL_OF_READONLY, allowed,
                                    nullptr, nullptr));
    if (!frames_) {
      *error = "frames.gpkg is not a GeoPackage GDAL can read";
      return false;
    }
    frames_layer_ = frames_->GetLayerByName("frames");
    if (frames_layer_ == nullptr) {
      frames_.reset();
      *error = "frames.gpkg has no layer \"frames\"";
      return false;
    }
    return true;
  }

  // Reads the window [x, x+w) x [y, y+h) of this level (dataset pixels) of `band` into `out`
  // (line stride `line_px` samples), leaving samples of absent tiles untouched.
  CPLErr ReadWindow(int band, int x, int y, int w, int h, void* out, int line_px) {
    const int t = index_->tile_size;
    const int bytes = GDALGetDataTypeSizeBytes(index_->type);
    const int64_t ax0 = col_offset_px_ + x, ay0 = row_offset_px_ + y;  // Level-l absolute.
    const int64_t ax1 = ax0 + w, ay1 = ay0 + h;
    const auto floor_div = [t](int64_t v) { return v >= 0 ? v / t : -((-v + t - 1) / t); };
    for (int64_t tr = floor_div(ay0); tr <= floor_div(ay1 - 1); ++tr) {
      for (int64_t tc = floor_div(ax0); tc <= floor_div(ax1 - 1); ++tc) {
        if (!HasTile(tr, tc)) continue;  // Missing: nodata, alpha 0.
        const int64_t ix0 = std::max(ax0, tc * t), ix1 = std::min(ax1, tc * t + t);
        const int64_t iy0 = std::max(ay0, tr * t), iy1 = std::min(ay1, tr * t + t);
        GByte* dst = static_cast<GByte*>(out) +
                     ((iy0 - ay0) * static_cast<int64_t>(line_px) + (ix0 - ax0)) * bytes;
        if (ReadTile(band, tr, tc, static_cast<int>(ix0 - tc * t), static_cast<int>(iy0 - tr * t),
                     static_cast<int>(ix1 - ix0), static_cast<int>(iy1 - iy0), dst,
                     line_px) != CE_None) {
          return CE_Failure;
        }
      }
    }
    return CE_None;
  }

  std::vector<std::unique_ptr<IrmosaicDataset>> overviews_;
  std::shared_ptr<const StoreIndex> index_;  // As opened: the grid, extent and georeferencing.
  std::shared_ptr<LiveIndex> live_;          // The tiles present now.
  IrmosaicDataset* root_ = nullptr;          // The level-0 dataset (this one at level 0).
  int level_ = 0;

 private:
  bool HasTile(int64_t row, int64_t col) const {
    const StoreIndex& now = *live_->index;
    return level_ < static_cast<int>(now.levels.size()) &&
           now.levels[level_].count({row, col}) != 0;
  }

  CPLErr ReadTile(int band, int64_t row, int64_t col, int x, int y, int w, int h, GByte* dst,
                  int line_px) {
    const std::string relative = "tiles/" + std::to_string(level_) + "/" + std::to_string(row) +
                                 "_" + std::to_string(col) + ".tif";
    const std::string path = index_->root + "/" + relative;
    // A tile named by the manifest must be a file inside the store, symlinks resolved.
    const std::string real = RealPath(path);
    if (real.empty() || real.compare(0, index_->root.size() + 1, index_->root + "/") != 0) {
      CPLError(CE_Failure, CPLE_OpenFailed,
               "IRMOSAIC: tile %s is missing or lies outside the store %s", relative.c_str(),
               index_->root.c_str());
      return CE_Failure;
    }
    const char* const allowed[] = {"GTiff", nullptr};
    GDALDatasetUniquePtr tile(GDALDataset::Open(real.c_str(), GDAL_OF_RASTER | GDAL_OF_READONLY,
                                                allowed, nullptr, nullptr));
    if (!tile) {
      CPLError(CE_Failure, CPLE_OpenFailed, "IRMOSAIC: cannot read tile %s of store %s",
               relative.c_str(), index_->root.c_str());
      return CE_Failure;
    }
    const int t = index_->tile_size;
    if (tile->GetRasterXSize() != t || tile->GetRasterYSize() != t || tile->GetRasterCount() < 2 ||
        tile->GetRasterBand(band)->GetRasterDataType() != index_->type) {
      CPLError(CE_Failure, CPLE_AppDefined,
               "IRMOSAIC: tile %s is not a %d x %d two-band %s raster as the manifest says",
               relative.c_str(), t, t, GDALGetDataTypeName(index_->type));
      return CE_Failure;
    }
    const int bytes = GDALGetDataTypeSizeBytes(index_->type);
    return tile->GetRasterBand(band)->RasterIO(GF_Read, x, y, w, h, dst, w, h, index_->type, bytes,
                                               static_cast<GSpacing>(line_px) * bytes, nullptr);
  }

  int64_t col_offset_px_ = 0, row_offset_px_ = 0;
  OGRSpatialReference srs_;
  GDALDatasetUniquePtr frames_;  // Owns frames_layer_.
  OGRLayer* frames_layer_ = nullptr;
};

IrmosaicBand::IrmosaicBand(IrmosaicDataset* dataset, int band) {
  poDS = dataset;
  nBand = band;
  eDataType = dataset->index_->type;
  nBlockXSize = std::min(dataset->index_->tile_size, dataset->GetRasterXSize());
  nBlockYSize = std::min(dataset->index_->tile_size, dataset->GetRasterYSize());
  eAccess = GA_ReadOnly;
  SetDescription(band == 1 ? "mosaic" : "coverage (alpha)");
}

CPLErr IrmosaicBand::IReadBlock(int block_x, int block_y, void* data) {
  try {
    auto* ds = static_cast<IrmosaicDataset*>(poDS);
    const int bytes = GDALGetDataTypeSizeBytes(eDataType);
    std::memset(data, 0, static_cast<size_t>(nBlockXSize) * nBlockYSize * bytes);
    const int x = block_x * nBlockXSize, y = block_y * nBlockYSize;
    const int w = std::min(nBlockXSize, nRasterXSize - x);
    const int h = std::min(nBlockYSize, nRasterYSize - y);
    return ds->ReadWindow(nBand, x, y, w, h, data, nBlockXSize);
  } catch (const std::exception& e) {
    CPLError(CE_Failure, CPLE_AppDefined, "IRMOSAIC: %s", e.what());
  } catch (...) {
    CPLError(CE_Failure, CPLE_AppDefined, "IRMOSAIC: unknown error reading a block");
  }
  return CE_Failure;
}

CPLErr IrmosaicBand::IRasterIO(GDALRWFlag rw, int x, int y, int w, int h, void* data, int buf_w,
                               int buf_h, GDALDataType buf_type, GSpacing pixel_space,
                               GSpacing line_space, GDALRasterIOExtraArg* extra) {
  if (rw == GF_Read && nBand == 1) {
    try {
      static_cast<IrmosaicDataset*>(poDS)->root_->Refresh();
    } catch (const std::exception& e) {
      CPLDebug("IRMOSAIC", "refresh failed: %s", e.what());
    }
  }
  return GDALRasterBand::IRasterIO(rw, x, y, w, h, data, buf_w, buf_h, buf_type, pixel_space,
                                   line_space, extra);
}

int IrmosaicBand::GetOverviewCount() {
  return static_cast<int>(static_cast<IrmosaicDataset*>(poDS)->overviews_.size());
}

GDALRasterBand* IrmosaicBand::GetOverview(int i) {
  auto& overviews = static_cast<IrmosaicDataset*>(poDS)->overviews_;
  if (i < 0 || i >= static_cast<int>(overviews.size())) return nullptr;
  return overviews[i]->GetRasterBand(nBand);
}

// Opens a store for `info`; nullptr with a CPLError on refusal.
GDALDataset* OpenStore(GDALOpenInfo* info) {
  if (!Identify(info)) return nullptr;
  if (info->eAccess == GA_Update) {
    CPLError(CE_Failure, CPLE_NotSupported,
             "IRMOSAIC: the store %s is read-only through GDAL; it is written by irmosaic "
             "(TileStore) alone",
             info->pszFilename);
    return nullptr;
  }
  const std::string manifest = ManifestPathOf(info);
  auto index = std::make_shared<StoreIndex>();
  const std::string folder = CPLGetPath(manifest.c_str());
  index->root = RealPath(folder.empty() ? "." : folder);
  if (index->root.empty()) {
    CPLError(CE_Failure, CPLE_OpenFailed, "IRMOSAIC: cannot resolve the folder of %s",
             manifest.c_str());
    return nullptr;
  }
  // GDAL passes the kinds the caller accepts (gdalinfo: raster, ogrinfo: vector, GDALOpenEx
  // with no kind: all). The raster needs tiles; the footprints layer alone does not.
  const bool want_raster = (info->nOpenFlags & GDAL_OF_RASTER) != 0;
  const bool want_vector = (info->nOpenFlags & GDAL_OF_VECTOR) != 0;
  // The manifest's identity is taken before it is read: a publish in between is then taken by
  // the first refresh, never missed.
  auto live = std::make_shared<LiveIndex>();
  live->manifest_path = manifest;
  live->live = CPLFetchBool(info->papszOpenOptions, "LIVE", true);
  live->Replaced();
  std::string text, error;
  bool not_a_store = false;
  if (!ReadSmallFile(manifest, &text, &error) ||
      !ParseManifest(text.data(), text.size(), index.get(), &error, &not_a_store,
                     /*allow_empty=*/!want_raster)) {
    if (!not_a_store) {
      CPLError(CE_Failure, CPLE_OpenFailed, "IRMOSAIC: refusing %s: %s", manifest.c_str(),
               error.c_str());
    }
    return nullptr;
  }
  live->index = index;
  auto dataset = std::make_unique<IrmosaicDataset>(live, 0, want_raster);
  dataset->SetDescription(info->pszFilename);
  if (want_vector && !dataset->OpenFrames(&error)) {
    // A raster client loses nothing; a vector-only client has nothing to read.
    if (!want_raster) {
      CPLError(CE_Failure, CPLE_OpenFailed, "IRMOSAIC: no footprints layer in %s: %s",
               info->pszFilename, error.c_str());
      return nullptr;
    }
    CPLDebug("IRMOSAIC", "no footprints layer: %s", error.c_str());
  }
  dataset->SetIndexMetadata(*index);
  return dataset.release();
}

GDALDataset* Open(GDALOpenInfo* info) {
  try {
    return OpenStore(info);
  } catch (const std::exception& e) {
    CPLError(CE_Failure, CPLE_AppDefined, "IRMOSAIC: cannot open %s: %s", info->pszFilename,
             e.what());
  } catch (...) {
    CPLError(CE_Failure, CPLE_AppDefined, "IRMOSAIC: cannot open %s", info->pszFilename);
  }
  return nullptr;
}

int IdentifyNoThrow(GDALOpenInfo* info) {
  try {
    return Identify(info);
  } catch (...) {
    return FALSE;
  }
}

}  // namespace
}  // namespace irmosaic

extern "C" void GDALRegister_IRMOSAIC() {
  if (!GDAL_CHECK_VERSION("IRMOSAIC")) return;
  if (GDALGetDriverByName(irmosaic::kDriverName) != nullptr) return;
  auto* driver = new GDALDriver();
  driver->SetDescription(irmosaic::kDriverName);
  driver->SetMetadataItem(GDAL_DCAP_RASTER, "YES");
  driver->SetMetadataItem(GDAL_DCAP_VECTOR, "YES");
  driver->SetMetadataItem(GDAL_DMD_LONGNAME, "irmosaic live mosaic store (read-only)");
  driver->SetMetadataItem(GDAL_DMD_HELPTOPIC, "docs/store.md#gdal-plug-in");
  driver->SetMetadataItem(GDAL_DCAP_VIRTUALIO, "NO");
  driver->SetMetadataItem(
      GDAL_DMD_OPENOPTIONLIST,
      "<OpenOptionList>"
      "  <Option name='LIVE' type='boolean' default='YES' description='Follow the store while "
      "it is written: reads take each newly published generation (tiles inside the opened "
      "extent)'/>"
      "</OpenOptionList>");
  driver->pfnIdentify = irmosaic::IdentifyNoThrow;
  driver->pfnOpen = irmosaic::Open;
  GetGDALDriverManager()->RegisterDriver(driver);
}

extern "C" int IrmosaicDriverOpenForFuzzing(const char* manifest_path) {
  try {
    GDALRegister_IRMOSAIC();
    const char* const allowed[] = {irmosaic::kDriverName, nullptr};
    GDALDatasetUniquePtr ds(GDALDataset::Open(manifest_path, GDAL_OF_RASTER | GDAL_OF_READONLY,
                                              allowed, nullptr, nullptr));
    if (!ds) return -1;
    std::vector<double> block(256 * 256);
    const int w = std::min(256, ds->GetRasterXSize()), h = std::min(256, ds->GetRasterYSize());
    for (int b = 1; b <= ds->GetRasterCount(); ++b) {
      if (ds->GetRasterBand(b)->RasterIO(GF_Read, 0, 0, w, h, block.data(), w, h, GDT_Float64, 0, 0,
                                         nullptr) != CE_None) {
        return -1;
      }
    }
    return 0;
  } catch (...) {
    return -1;
  }
}

extern "C" int IrmosaicParseManifestForFuzzing(const char* data, size_t size) {
  try {
    irmosaic::StoreIndex index;
    std::string error;
    bool not_a_store = false;
    return irmosaic::ParseManifest(data, size, &index, &error, &not_a_store) ? 0 : -1;
  } catch (...) {
    return -1;
  }
}
