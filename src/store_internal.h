#pragma once
// Private helpers of the TileStore (src/tile_store.cc): the files of a store and how each is
// written. Not installed; see docs/store.md for the layout and the manifest schema.

#include <array>
#include <cstdint>
#include <filesystem>
#include <map>
#include <opencv2/core.hpp>
#include <optional>
#include <set>
#include <string>
#include <utility>
#include <vector>

#include "irmosaic/tile_store.h"
#include "mat_pool.h"

namespace irmosaic::store {

inline constexpr const char* kFormatName = "irmosaic-store";
// 2: each level lists its tiles as blocks of kVrtBlockTiles^2 with a presence bitmap
// (docs/store.md); 1 listed every tile. Readers take both.
inline constexpr int kFormatVersion = 2;
inline constexpr int kBlockSize = 256;  // Internal GeoTIFF tiling (or the tile size if smaller).

using TileIndex = std::pair<int64_t, int64_t>;  // (row, col), signed.
using TileSet = std::set<TileIndex>;

// A tile in memory: samples of the store's type and coverage as CV_8U 0/255.
struct TileImage {
  cv::Mat data;
  cv::Mat alpha;
  bool empty() const { return data.empty(); }
};

// Alpha value meaning "covered" in files: 65535 for UInt16 (GDAL's default alpha maximum for
// 16-bit), 255 otherwise (GDAL and QGIS read a Byte or Float32 alpha on a 0..255 scale).
double AlphaMaxOf(PixelType type);
PixelType PixelTypeFromName(const std::string& name);  // Throws Error on an unknown name.

TileImage EmptyTile(int tile_size, PixelType type);

// Buffers for the tiles of one store (full size, and halved for the next level): a store makes
// and drops tiles all flight (cache, writer, overviews), so they come from pools (mat_pool.h)
// instead of the heap. Up to `capacity` tiles of each size are pooled.
struct TilePools {
  TilePools(int tile_size, PixelType type, size_t capacity);
  TileImage Blank();      // Full size, contents undefined.
  TileImage Empty();      // Full size, zeros (uncovered).
  TileImage HalfBlank();  // Half size, contents undefined.
  MatPool data, alpha, half_data, half_alpha;
};
// With pools, EmptyTile, ReadTile and HalveTile take their buffers from them.
TileImage EmptyTile(TilePools* pools);

// Path of tile (row, col) of `level`, relative to the store: tiles/<level>/<row>_<col>.tif.
std::string TileRelativePath(int level, const TileIndex& tile);
// GDAL geotransform of a tile of `level` (pixel size gsd * 2^level).
void TileGeoTransform(double gsd_m, int tile_size, int level, const TileIndex& tile, double gt[6]);

// How WriteTileAtomic encodes a tile. kDirect: for the store's own layout (ZSTD, Byte or UInt16,
// little-endian, the tile a whole number of blocks) libtiff writes the file's structure while
// the store applies the predictor (SSE2) and compresses each block with libzstd itself, handing
// libtiff the finished blocks (TIFFWriteRawTile); the georeferencing tags are those GDAL wrote
// for the first tile of the CRS (that tile goes through GDAL), with the tile's own geotransform.
// Anything else goes through GDAL's GTiff driver, as with kGdal. Both give files GDAL reads as
// the same samples, georeference and structure. Why: libtiff 4.5 applies the predictor one byte
// at a time and GDAL copies each block on its way (docs/store.md, "Writing tiles").
enum class TileEncoding { kDirect, kGdal };

struct TileWriteSettings {
  PixelType type = PixelType::kUInt16;
  std::string compression = "ZSTD";
  int compression_level = 1;
  std::string crs_wkt;
  bool durable = false;
  TileEncoding encoding = TileEncoding::kDirect;
};

// The tile's blocks (kBlockSize, or the tile if smaller) as bits: block (row r, column c) of a
// tile n blocks wide is bit r * n + c. Tiles of more than 64 blocks have no mask (all change).
using BlockMask = uint64_t;
inline constexpr BlockMask kAllBlocks = ~BlockMask{0};
// The blocks of a tile of `tile_size` that `rect` (tile pixels) overlaps.
BlockMask BlocksOverlapping(const cv::Rect& rect, int tile_size);

// Where a tile file written by the direct encoder holds its compressed blocks (TIFF tile order:
// the data band's blocks, then the alpha band's), and which file that was (device, inode, size),
// so that the next write of the same tile copies the blocks that did not change instead of
// encoding them again.
struct TileFileLayout {
  uint64_t device = 0, inode = 0;
  int64_t size = 0;
  std::vector<uint64_t> offsets, lengths;
};
// What the file at a tile's path holds and which blocks of the tile to write differ from it.
struct TileReuse {
  const TileFileLayout* previous = nullptr;
  BlockMask changed = kAllBlocks;
};

// Writes a tile GeoTIFF to a temporary name beside `path` and renames it into place. Returns the
// file's size. Throws OutputError naming the file on any failure (the old file stays). With
// `reuse`, a direct write copies the unchanged blocks' bytes from the file now at `path` when
// that is still the file `reuse->previous` describes (else it encodes every block); with
// `layout`, a direct write says where its blocks went (layout->offsets empty otherwise).
int64_t WriteTileAtomic(const std::filesystem::path& path, const TileImage& tile,
                        const double gt[6], const TileWriteSettings& settings,
                        const TileReuse* reuse = nullptr, TileFileLayout* layout = nullptr);
// Blocks this thread's direct writes copied from the previous file, and blocks they encoded
// (both bands counted once per block), for tests and statistics.
int64_t BlocksCopied();
int64_t BlocksEncoded();
// Tiles this thread has written with the direct encoder (WriteTileAtomic's kDirect path), for
// tests.
int64_t DirectTileWrites();
// TIFF's horizontal differencing (predictor 2) of one row of n samples: out[0] = in[0], then
// each sample minus the one before it, wrapping.
void HorizontalDifferencing(const uint8_t* in, uint8_t* out, int n);
void HorizontalDifferencing(const uint16_t* in, uint16_t* out, int n);
// How ReadTile decodes a tile's samples. kDirect: GDAL opens the file (its header, shape and
// block table) and, when the blocks are the store's own layout (ZSTD with the horizontal
// predictor, band-interleaved, Byte or UInt16, little-endian), ReadTile decompresses them with
// libzstd and undoes the predictor itself; anything else, and any block that does not decode,
// goes through GDAL's RasterIO as with kGdal. Both give the same samples. Why: libtiff 4.5
// undoes the predictor one byte at a time through memory (each add waits for the store before
// it), the largest single cost of reading a tile back (docs/store.md, "Reading tiles back").
enum class TileDecoding { kDirect, kGdal };

// Reads a tile written by WriteTileAtomic. Throws OutputError if unreadable or of another shape.
TileImage ReadTile(const std::filesystem::path& path, int tile_size, PixelType type,
                   TilePools* pools = nullptr, TileDecoding decoding = TileDecoding::kDirect);
// Tiles this thread has read with the direct decoder (ReadTile's kDirect path taken), for tests.
int64_t DirectTileReads();

// TIFF's horizontal differencing (predictor 2) undone over one row of n samples in place: each
// sample becomes the wrapped sum of itself and all before it in the row.
void UndoHorizontalDifferencing(uint8_t* row, int n);
void UndoHorizontalDifferencing(uint16_t* row, int n);

// Writes `content` to path through a temporary name and a rename. Throws OutputError.
void WriteFileAtomic(const std::filesystem::path& path, const std::string& content, bool durable);
// True for names of temporaries left by an interrupted write (".<name>.tmp<pid>").
bool IsTemporaryName(const std::string& filename);

// Halves a tile (2x2 coverage-weighted mean); result is tile_size/2 square.
TileImage HalveTile(const TileImage& tile, TilePools* pools = nullptr);

// The level VRTs (mosaic.vrt and the overview VRTs) list blocks of kVrtBlockTiles x
// kVrtBlockTiles tiles, each block its own VRT beside its tiles with the block's whole extent
// as geometry: a publish rewrites the blocks that gained tiles and a level VRT of one source per
// block, not one per tile (a flight's index grows with its length; an hour has ~10^5 tiles).
inline constexpr int64_t kVrtBlockTiles = 16;
using BlockIndex = std::pair<int64_t, int64_t>;  // (block row, block col), signed.
BlockIndex BlockOf(const TileIndex& tile);
// One block's tiles: a 16-bit mask per tile row of the block, top row first, the block's first
// column the most significant bit (the manifest's bitmaps, docs/store.md).
using BlockRows = std::array<uint16_t, kVrtBlockTiles>;
int TilesIn(const BlockRows& rows);

// Tile bounds [row0, row1) x [col0, col1); the tile (0,0) alone if there are no tiles.
struct TileBounds {
  int64_t row0 = 0, row1 = 1, col0 = 0, col1 = 1;
};

// The tiles of one level, held as the blocks that have any, each with its bitmap: what a publish
// writes of the index (the block VRTs that gained tiles, a level VRT of a source per block, the
// manifest's bitmaps) and the bounds then cost a pass over the blocks, not over every tile of
// the flight (an hour has ~10^5 tiles; a full block holds 256).
class LevelTiles {
 public:
  bool insert(const TileIndex& tile);  // True if the tile was not there.
  bool erase(const TileIndex& tile);   // True if the tile was there.
  bool contains(const TileIndex& tile) const;
  size_t count(const TileIndex& tile) const { return contains(tile) ? 1 : 0; }
  bool empty() const { return size_ == 0; }
  size_t size() const { return size_; }
  // Only blocks with at least one tile, in (block row, block col) order.
  const std::map<BlockIndex, BlockRows>& blocks() const { return blocks_; }
  // Adds a block's bitmap (OR), e.g. as read from a manifest.
  void InsertBlock(const BlockIndex& block, const BlockRows& rows);
  // Every tile, block by block, each block's in (row, col) order.
  std::vector<TileIndex> tiles() const;
  TileBounds bounds() const;
  bool operator==(const LevelTiles& other) const { return blocks_ == other.blocks_; }

 private:
  std::map<BlockIndex, BlockRows> blocks_;
  size_t size_ = 0;
};

// The published index of a store: what manifest.json holds.
struct Manifest {
  int64_t generation = 0;
  StoreGeoreference georef;
  int tile_size = 512;
  int block_size = kBlockSize;
  PixelType type = PixelType::kUInt16;
  std::string compression;
  std::vector<LevelTiles> levels;  // levels[0]: level-0 tiles; then overview levels.
  int64_t frame_count = 0;
  double time_min_s = 0.0, time_max_s = 0.0;
  std::string created_utc, published_utc;
  std::string application_json;               // Caller's state, verbatim JSON ("" = none).
  double display_lo = 0.0, display_hi = 0.0;  // Ramp range of the .qlr (hi <= lo: unknown).
  std::vector<std::string> overview_vrts;     // Relative paths, index l-1 for level l.
  std::string level0_vrt;  // Relative path of the VRT over level 0's blocks ("" = none yet).
  // The extent the writer foresees for the whole flight (level-0 pixels col_min, row_min,
  // col_max, row_max, half-open), when it knows it (TileStore::SetPlannedBoundsPx).
  std::optional<std::array<int64_t, 4>> planned_bounds_px;
  // Frame records put before this generation and not yet in frames.gpkg (it follows every
  // overview_interval_s): with frames.gpkg's, the records of this generation's frames. A resume
  // puts them back; without them a kill lost the records of the last seconds' frames.
  std::vector<FrameRecord> frames_pending;
  // Level-0 tiles whose overviews may not show their latest content yet (overviews follow every
  // overview_interval_s, in slices): a resume brings the overviews up to date from them.
  std::vector<TileIndex> overviews_owed;
};
std::string ManifestToJson(const Manifest& manifest);
// Parses manifest.json; throws InputError naming the file if it is not a store manifest.
Manifest ReadManifest(const std::filesystem::path& path);

// File name of a block VRT, beside the level's tiles: block_r<row>_c<col>.vrt.
std::string BlockVrtName(const BlockIndex& block);
// One block's VRT at `level`: the block's extent, a source per tile of the level in it.
std::string BuildBlockVrt(const Manifest& manifest, int level, const BlockIndex& block);
// The extent of mosaic.vrt and its overview VRTs for tiles painted over `painted`: grown on
// each axis to whole multiples of a step, a power of two no larger than a sixteenth of that
// axis's span (1 tile below 32 tiles), so that a growing mosaic changes the VRTs' extent
// ~16 times per doubling of its span instead of at nearly every publish; the padding is
// transparent (alpha 0) and at most a sixteenth of the span on each side.
TileBounds VrtBounds(const TileBounds& painted);
// The VRT of one level over `bounds` (level-0 tiles) as XML text, for a file in tiles/ (level 0,
// LevelVrtPath) or tiles/<level>/ (the overviews): one source per block VRT of the level. It
// carries no generation, so it is rewritten only when its blocks or extent change.
std::string BuildLevelVrt(const Manifest& manifest, int level, const TileBounds& bounds);
// Where the VRT of `level` over `bounds` lives, relative to the store: for level 0
// tiles/level0_r<row0>_c<col0>_<rows>x<cols>.vrt, above it
// tiles/<level>/overview_r<row0>_c<col0>_<rows>x<cols>.vrt. Named by the extent, so a reader
// holding an older mosaic.vrt never meets a VRT of another geometry.
std::string LevelVrtPath(int level, const TileBounds& bounds);
// mosaic.vrt: the generation (metadata item IRMOSAIC_GENERATION), one source per band (level
// 0's VRT, `level0_path`) and the overview VRTs: a few KiB however large the store, so the one
// index file written at every publish does not grow with the flight.
std::string BuildMosaicVrt(const Manifest& manifest, const TileBounds& bounds,
                           const std::string& level0_path,
                           const std::vector<std::string>& overview_paths);
// The QGIS layer definition: the mosaic with a thermal ramp and auto-refresh, and the frames.
// display_lo/hi: the ramp's initial range (e.g. the data's 2-98 % percentiles); QGIS then
// follows what the canvas shows. `live`: the mosaic is the store itself through the IRMOSAIC
// GDAL plug-in (./manifest.json), which follows the store at every repaint; otherwise
// ./mosaic.vrt, which any GDAL reads but QGIS 3.22 only re-reads on a reload.
std::string BuildQlr(const std::string& layer_name, const std::string& crs_wkt, double display_lo,
                     double display_hi, bool live = false);
// 2 % and 98 % percentiles of the covered samples of some tiles; false if none is covered.
bool CoveredPercentiles(const std::vector<const TileImage*>& tiles, double* lo, double* hi);

// A new, empty frames.gpkg (built under a temporary name, renamed into place; WAL mode).
void CreateFramesGpkg(const std::filesystem::path& path, const std::string& crs_wkt, bool durable);
// Inserts or replaces `changed` in frames.gpkg in place, in one SQLite transaction (WAL mode), so
// the cost follows the change, not the file; creates the file first if it is missing. While
// another connection holds the file locked ("database is locked"), tries again for up to
// `locked_budget_ms`, then returns false with nothing written (the caller keeps the records for
// a later write); true once written. Any other failure throws OutputError.
bool WriteFramesGpkg(const std::filesystem::path& path, const std::string& crs_wkt,
                     const std::vector<FrameRecord>& changed, bool durable, int locked_budget_ms);
// How many times WriteFramesGpkg found frames.gpkg locked by another connection for a moment
// and tried again (this process, since it started).
int64_t FramesGpkgBusyRetries();
// How long a live publish (250 ms) and the closing one (10 s) try again while frames.gpkg is
// locked (TileStore's writer). Tests shorten the closing wait.
inline constexpr int kFramesGpkgClosingLockBudgetMs = 10000;
int FramesGpkgLiveLockBudgetMs();
int FramesGpkgClosingLockBudgetMs();
void SetFramesGpkgClosingLockBudgetMsForTesting(int ms);
// Back to SQLite's rollback journal when the store closes: a finished frames.gpkg is one file,
// readable from read-only media (a WAL-mode file needs its -shm beside it).
void SettleFramesGpkg(const std::filesystem::path& path);
// All records of a frames.gpkg (empty if the file is absent).
std::vector<FrameRecord> ReadFramesGpkg(const std::filesystem::path& path);

std::string UtcNow();

}  // namespace irmosaic::store
