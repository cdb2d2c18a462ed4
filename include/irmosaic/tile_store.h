#pragma once

#include <Eigen/Core>
#include <array>
#include <chrono>
#include <cstdint>
#include <functional>
#include <memory>
#include <opencv2/core.hpp>
#include <optional>
#include <string>
#include <vector>

#include "irmosaic/export.h"

namespace irmosaic {

// Sample type of the mosaic; follows the input video (8-bit, 16-bit radiometric, float).
enum class PixelType { kByte, kUInt16, kFloat32 };

// OpenCV depth (CV_8U, CV_16U, CV_32F) and GDAL name ("Byte", "UInt16", "Float32").
IRMOSAIC_EXPORT int CvDepthOf(PixelType type);
IRMOSAIC_EXPORT const char* GdalTypeNameOf(PixelType type);

// Where the mosaic sits on Earth: the mosaic plane's origin, pixel size and CRS.
struct StoreGeoreference {
  double origin_lat_deg = 0.0;
  double origin_lon_deg = 0.0;
  double gsd_m = 0.5;   // Level-0 pixel size on the plane, metres.
  std::string crs_wkt;  // The plane's CRS, LocalFrame::CrsWkt().
};

// What a Paint brings: new content (a frame placed for the first time), or a refresh of content
// already there (a frame re-rendered at a refined placement), which may reach the disk later.
enum class PaintKind { kNew, kRefresh };

// Diagnostics of one publish of a TileStore (TileStoreOptions::on_publish): when it was asked
// for and ran, and what it did. For tracing a publish latency to its parts (bench/flight_bench
// prints the slowest frames' figures); nothing in the store depends on it.
struct PublishReport {
  int64_t generation = 0;  // The generation published (or not, if `failed`).
  // The oldest and newest RequestPublish() this publish answers (the writer folds requests
  // that waited together into one publish), when it started and when it finished (the time
  // TileStore::PublishedAt gives its generations).
  std::chrono::steady_clock::time_point first_request, last_request, started, finished;
  // Slices the writer ran since the previous publish (refreshed tiles, overview updates), and
  // their wall time: work a request may have waited behind.
  int refresh_slices = 0, overview_slices = 0;
  double slices_ms = 0.0;
  int level0_tiles = 0;     // Level-0 tiles this publish wrote,
  int refreshed_tiles = 0;  // of them refreshed ones it took (more waited than the bound).
  // The overviews and frames.gpkg: whether this publish started an update (by the clock, or
  // early: the memory bound), and whether it did the update whole inside itself (delaying its
  // frames: past twice the bound, with overview_interval_s 0, and at Close()), with the
  // overview tiles it wrote then.
  bool overview_update = false, overview_update_early = false, overview_update_in_publish = false;
  int overview_tiles = 0;
  bool frames_gpkg = false;  // frames.gpkg written by this publish.
  // frames.gpkg was due but another program held it locked past a short wait: its records went
  // in manifest.json (frames.pending) instead, and the next update tries again.
  bool frames_gpkg_locked = false;
  double index_ms = 0.0;  // Wall time in the index (VRTs, manifest.json).
  double cpu_ms = 0.0;    // The writer's CPU time in this publish,
  // and the time it waited for a CPU while runnable (Linux's /proc/thread-self/schedstat; 0
  // where not reported). The rest of the wall time it was blocked: on the disk, or on a lock.
  double run_queue_ms = 0.0;
  bool failed = false;  // Not published (e.g. a full disk); retried with the next one.
};

// Configuration of a TileStore.
struct TileStoreOptions {
  std::string path;  // The store folder, e.g. out/flight.irmosaic.
  // kCreate refuses an existing store, kOverwrite deletes it first, kResume continues it.
  enum class Mode { kCreate, kOverwrite, kResume } mode = Mode::kCreate;
  int tile_size = 512;                        // Pixels per tile side, a multiple of 16 (>= 64).
  PixelType pixel_type = PixelType::kUInt16;  // Ignored on kResume (the store's own type wins).
  // Tile compression: "ZSTD" (default, chosen by bench/store_bench), "DEFLATE", "LZW" or "NONE";
  // a horizontal predictor is always used (floating-point predictor for Float32).
  std::string compression = "ZSTD";
  int compression_level = 1;  // ZSTD 1..22 / DEFLATE 1..9; low levels keep the writer fast.
  int overview_levels = -1;   // Overview levels above level 0; -1: grow with the extent.
  // Overviews and frames.gpkg are brought up to date at most this often, seconds (0: on
  // every publish), or sooner when more than 4 x max_cached_tiles level-0 tiles wait for them
  // (their images wait in memory, halved: a quarter of a tile each); level-0 tiles and the index
  // are published every time, and Close() brings everything up to date. Zoomed-out views may lag by
  // this much plus the update's own time; the writer's work per publish no longer includes the
  // overview pyramid and the growing frames.gpkg.
  double overview_interval_s = 0.0;
  // With overview_interval_s > 0 an overview update runs between publishes, in slices of at
  // most this many overview tiles (a level the extent just gained is built in one): one slice
  // after each publish and more while no publish is asked for, so a frame's publish waits for
  // one slice at most, not for the whole pyramid. An update the memory bound starts early runs
  // in slices too; past twice that bound (Stats::overview_updates_in_publish), with
  // overview_interval_s 0 and at Close(), the overviews are brought up to date within the
  // publish.
  int overview_slice_tiles = 8;
  // Tiles a refresh (Paint with PaintKind::kRefresh: the optimizer's re-renders) changed, and
  // nothing new since their last write, are written between publishes, in slices of at most this
  // many tiles (one slice after each publish, more while no publish is asked for), in place: a
  // publish carries the tiles of new frames only, so their latency does not include a solve's
  // burst of re-rendered tiles. More than max_cached_tiles such tiles waiting, and the publish
  // takes the least recently painted of them, down to this many fewer than max_cached_tiles;
  // Close() takes them all. 0: every publish writes every changed tile.
  int refresh_slice_tiles = 8;
  // A refreshed tile is ready for a slice once this many publishes have passed since it was last
  // painted (1: the next publish): the re-renders of neighbouring frames (a sweep's frames
  // leaving the optimization window one per new frame, a solve's burst) repaint the same tiles
  // over a few seconds, and a tile written once they are done is written once, not once per
  // publish. The bound above still applies (waiting tiles stay in memory): at 25 fps the tiles
  // re-rendered within 2 s outnumber the default bound, so larger values made the publishes take
  // them (latency up, writer no cheaper; docs/benchmarks.md, "Session 35").
  int refresh_quiet_publishes = 1;
  // Memory bound: clean tiles beyond this leave memory, and an overview update starts early when
  // more than 4 times this many tiles wait for it (halved; in slices, or within the publish past
  // 8 times, counting an update under way).
  size_t max_cached_tiles = 64;
  bool durable = false;  // fsync each file before its rename (power-loss safety).
  // Every sync_interval_s seconds a thread of its own flushes the store's file system
  // (syncfs(2)), so published tiles are on the disk within about that long (a power loss keeps
  // them; the kernel's own write-back takes up to ~30 s), without the cost of `durable`. On ext4
  // without a journal it also keeps creating files cheap: there a new inode skips every inode
  // freed in the last 5 s, or 305 s while its inode table block is dirty, reading each one's
  // block, and a writer replacing ~250 tile files a second spent a third of its CPU in that scan
  // (docs/benchmarks.md, "Session 37"). 0: never.
  double sync_interval_s = 2.0;
  int writer_nice = 5;  // Writer thread's nice increment (0: same priority as the caller).
  std::string layer_name = "irmosaic";  // Name of the layers in the .qlr file.
  // Diagnostics: called after each publish, on the writer thread, with what it did
  // (PublishReport): after its files are written, before WaitPublished returns for its
  // generation. Keep it short: the writer waits for it; an exception it throws is ignored.
  // Empty: not called.
  std::function<void(const PublishReport&)> on_publish;

  // True if usable; otherwise *error says which option is wrong and why.
  bool IsValid(std::string* error) const;
};

// One frame's footprint and registration quality, kept in frames.gpkg.
struct FrameRecord {
  int64_t index = 0;                           // Frame index in the flight (unique key).
  double time_s = 0.0;                         // Frame time, seconds (POS time base).
  std::array<Eigen::Vector2d, 4> footprint_m;  // Corners on the mosaic plane, metres, in order.
  bool pos_only = false;                       // Placed from POS alone (no image registration).
  double residual_px = 0.0;                    // Registration residual (RMS), pixels; 0 if unknown.
  int inliers = 0;                             // Tie points kept by RANSAC.
  std::string status;                          // Free text: "registered", "pos_only", ...
};

// The live output: a tiled georeferenced mosaic on disk that GDAL tools and QGIS read while it
// grows. Level-0 tiles of tile_size pixels sit on a fixed grid of the mosaic plane (signed tile
// indices; tile (row, col) holds mosaic pixels [col*T, col*T+T) x [row*T, row*T+T)), each a
// compressed, internally tiled GeoTIFF with the mosaic CRS and an alpha band for coverage.
// Overview levels are tiles too. A background writer thread writes dirty tiles; RequestPublish()
// makes it replace the index (manifest.json, mosaic.vrt) atomically after the tiles it names, so
// a reader sees the last published state or the next one, never a torn file, and a crash at any
// moment leaves the last published state loadable (docs/store.md).
//
// Usage:
//   TileStoreOptions options;  options.path = "out/flight.irmosaic";
//   auto store = TileStore::Open(options, {lat0, lon0, 0.5, frame.CrsWkt()});
//   store->Paint(ortho, weight, origin_px);  // per frame, any thread
//   store->PutFrameRecord(record);
//   store->RequestPublish();                 // e.g. once a second
//   store->Close();                          // final publish; throws OutputError on failure
class IRMOSAIC_EXPORT TileStore {
 public:
  // Opens or creates the store. Throws InputError (bad options, existing store in kCreate mode,
  // store of another georeference in kResume mode) or OutputError (folder not writable), each
  // naming the path and the fix. On kResume the store's georeference must match `georef`.
  static std::unique_ptr<TileStore> Open(const TileStoreOptions& options,
                                         const StoreGeoreference& georef);
  // Opens an existing store's published state for reading only (no writer thread).
  static std::unique_ptr<TileStore> OpenReadOnly(const std::string& path);
  ~TileStore();  // Close()s; an error there is swallowed (call Close() to see it).
  TileStore(const TileStore&) = delete;
  TileStore& operator=(const TileStore&) = delete;

  // Blends a rendered patch into level 0: out = w*image + (1-w)*existing, where an uncovered
  // existing pixel counts as weight 0 (it takes the patch wherever w > 0). image has the store's
  // pixel type (CvDepthOf), one channel; weight is CV_32F in [0, 1], same size; top-left at
  // mosaic pixel origin_px (signed). Tiles under the patch where every weight is 0 are not
  // touched (not loaded, created or copied). Thread-safe. Blocks on disk only to reload a tile
  // that left memory, or when more than twice max_cached_tiles tiles wait for the writer
  // (back-pressure). kRefresh: see TileStoreOptions::refresh_slice_tiles (a tile not yet on disk
  // is published with the next generation either way).
  void Paint(const cv::Mat& image, const cv::Mat& weight, cv::Point origin_px,
             PaintKind kind = PaintKind::kNew);

  // Inserts or replaces (by index) a frame's footprint record; published with the next
  // generation.
  void PutFrameRecord(const FrameRecord& record);
  // Frame records known to the store (published ones after a resume, plus those put since),
  // by index. The store holds only those not yet written to frames.gpkg; the rest are read
  // from it (so memory does not grow with the flight). Throws InputError if frames.gpkg
  // cannot be read.
  std::vector<FrameRecord> FrameRecords() const;

  // Caller state saved in manifest.json with each publish (e.g. what `run --resume` needs);
  // any JSON text (checked here: InputError if it is not), stored verbatim under "application",
  // the manifest's last member. Empty: nothing.
  void SetApplicationState(const std::string& json_text);
  // The application state of the last published (or resumed) manifest.
  std::string application_state() const;

  // The extent the whole flight is expected to cover, level-0 mosaic pixels (e.g. from its POS
  // log); written to manifest.json as planned_bounds_px with the next publish and kept by a
  // resume. Readers that keep the store open and follow it (the IRMOSAIC GDAL plug-in, hence
  // QGIS) open it at this extent, so tiles painted later inside it show without a reopen. An
  // empty rectangle removes it. Only a hint: painting outside it is fine.
  void SetPlannedBoundsPx(const cv::Rect& mosaic_px);

  // Non-blocking: asks the writer thread to write dirty tiles, overviews, frames.gpkg, then
  // mosaic.vrt and manifest.json; returns the generation that publish will have.
  int64_t RequestPublish();
  // Blocks until `generation` is published; throws OutputError if the writer failed meanwhile.
  void WaitPublished(int64_t generation);
  // Generation of the last manifest written (0: nothing published yet).
  int64_t published_generation() const;
  // When the first publish of `generation` or a later one finished (the writer may fold
  // several requested generations into one publish); nullopt if none has yet, or if it is
  // older than the last 4096 publishes.
  std::optional<std::chrono::steady_clock::time_point> PublishedAt(int64_t generation) const;
  // How long the oldest requested publish that has not finished has waited, seconds; 0 when
  // the writer has published every request (or has failed and stopped publishing).
  double BacklogSeconds() const;

  // Reads a level-0 window back (as last painted, published or not). image gets the store's
  // pixel type, coverage is CV_8U 255 where painted, 0 elsewhere.
  void ReadWindow(const cv::Rect& mosaic_px, cv::Mat* image, cv::Mat* coverage) const;

  // Final publish, then joins the writer. Throws OutputError (full disk, permissions) naming
  // the file; what was published before stays valid. Idempotent.
  void Close();

  // Figures of the store's work so far.
  struct Stats {
    int64_t tiles_written = 0;           // Tile files written (all levels).
    int64_t overview_tiles_written = 0;  // Of those: overview tiles (levels above 0).
    int64_t bytes_written = 0;           // Bytes of tile files written.
    // Blocks (256 x 256, both bands) of the tiles written: copied from the tile's previous file,
    // unchanged since it was written, or encoded (docs/store.md, "Writing tiles").
    int64_t blocks_copied = 0;
    int64_t blocks_encoded = 0;
    int64_t syncs = 0;  // File system flushes (sync_interval_s) done.
    // Updates of frames.gpkg put off because another program held it locked (PublishReport::
    // frames_gpkg_locked); the records waited in manifest.json.
    int64_t frames_gpkg_locked = 0;
    int64_t publishes = 0;  // Generations published by this process.
    // Of those: publishes that started bringing the overviews (and frames.gpkg) up to date,
    // by the clock (overview_interval_s) or early, when the level-0 tiles owed to them passed
    // 4 x max_cached_tiles; and of the early ones, those done whole inside the publish
    // (delaying its frames) because the tiles waiting, with what an update under way still
    // owed, passed twice that (the slices behind a burst; Close's final update not counted).
    int64_t overview_updates = 0;
    int64_t overview_updates_early = 0;
    int64_t overview_updates_in_publish = 0;
    // Slices of overview work the writer ran between publishes (overview_slice_tiles).
    int64_t overview_slices = 0;
    bool overviews_pending = false;  // An overview update is under way or tiles wait for one.
    // Slices of refreshed tiles the writer ran between publishes, and the tiles they wrote
    // (refresh_slice_tiles; counted in tiles_written too); refreshed tiles waiting now.
    int64_t refresh_slices = 0;
    int64_t refresh_tiles_written = 0;
    size_t refresh_waiting = 0;
    int64_t tile_reloads = 0;    // Tiles read back from disk after leaving memory.
    int64_t overview_reads = 0;  // Overview tiles read from disk to update them.
    int64_t tile_copies = 0;  // Tiles Paint copied first, the writer still holding their buffers.
    double paint_ms_total = 0.0;  // Time spent in Paint() by callers,
    // of it waiting for the writer (back-pressure: more than 2 x max_cached_tiles tiles in
    // memory), and the Paint calls that waited.
    double paint_wait_ms_total = 0.0;
    int64_t paint_waits = 0;
    double writer_busy_ms = 0.0;  // Time the writer thread spent working.
    double writer_cpu_ms = 0.0;   // CPU time of that work (the load does not inflate it).
    // Of it, the kernel's (system time: creating, writing and renaming files). It depends on
    // the file system's state as much as on the work: on ext4 without a journal, creating a
    // file scans the inodes freed in the last seconds (docs/benchmarks.md, "Session 37"), so
    // a run right after a large store was deleted pays more.
    double writer_system_cpu_ms = 0.0;
    double index_ms_total = 0.0;    // Of the writer's time: writing the index (VRTs, manifest).
    int64_t index_bytes_total = 0;  // Bytes of index files written.
    double publish_p50_ms = 0.0;    // RequestPublish() to published, median.
    double publish_p99_ms = 0.0;    // ... 99th percentile.
    double publish_max_ms = 0.0;    // ... worst.
    size_t cached_tiles = 0;        // Level-0 tiles in memory now.
    // Frame records in memory now: those put and not yet written to frames.gpkg.
    size_t frame_records_held = 0;
    // Tiles whose images wait in memory for an overview update, under way or next, each halved
    // (upper levels' included): at most 8 x max_cached_tiles after each publish.
    size_t overview_owed_tiles = 0;
    size_t tiles_on_disk = 0;  // Level-0 tiles in the store.
  };
  Stats stats() const;

  // Level-0 bounds of the painted tiles, in mosaic pixels (empty if nothing painted).
  cv::Rect level0_bounds_px() const;
  const TileStoreOptions& options() const;
  const StoreGeoreference& georeference() const;
  PixelType pixel_type() const;

  struct Impl;

 private:
  explicit TileStore(std::unique_ptr<Impl> impl);
  std::unique_ptr<Impl> impl_;
};

// Tile index (row or column) holding mosaic pixel `px` for tiles of `tile_size` (floor division).
inline int64_t TileIndexOf(int64_t px, int tile_size) {
  return px >= 0 ? px / tile_size : -((-px + tile_size - 1) / tile_size);
}

}  // namespace irmosaic
