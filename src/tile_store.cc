// TileStore: the level-0 tile cache painted by callers, and the writer thread that publishes.
#include "irmosaic/tile_store.h"

#include <fcntl.h>
#include <gdal.h>
#include <pthread.h>
#include <sys/resource.h>
#include <sys/syscall.h>
#include <unistd.h>

#include <algorithm>
#include <array>
#include <atomic>
#include <bit>
#include <bitset>
#include <cerrno>
#include <chrono>
#include <cmath>
#include <condition_variable>
#include <cstdio>
#include <cstring>
#include <ctime>
#include <deque>
#include <functional>
#include <limits>
#include <list>
#include <map>
#include <memory>
#include <mutex>
#include <opencv2/core/hal/intrin.hpp>
#include <optional>
#include <set>
#include <thread>
#include <tuple>
#include <type_traits>
#include <unordered_map>
#include <utility>

#if defined(__x86_64__)
#include <immintrin.h>
#endif

#include "irmosaic/error.h"
#include "nlohmann/json.hpp"
#include "simd_dispatch.h"
#include "store_internal.h"
#include "thread_priority.h"

namespace irmosaic {

// Level-0 tiles that may wait for a deferred overview update, per cached tile: they wait halved
// (a quarter of a tile's memory), so 4 per cached tile hold what the cache does. At 1 per
// cached tile (until session 16) a 25 fps flight with re-renders passed the bound every ~0.75 s
// and 38 of 40 overview updates in 30 s came early instead of every overview_interval_s
// (docs/benchmarks.md, "Session 16"). Past it an update starts in slices; past twice it, waiting
// and under way together, a publish does the update itself (PublishOnce).
constexpr size_t kOwedPerCachedTile = 4;

namespace fs = std::filesystem;
using store::TileImage;
using store::TileIndex;
using store::TileSet;

int CvDepthOf(PixelType type) {
  switch (type) {
    case PixelType::kByte:
      return CV_8U;
    case PixelType::kUInt16:
      return CV_16U;
    case PixelType::kFloat32:
      return CV_32F;
  }
  return CV_8U;
}

const char* GdalTypeNameOf(PixelType type) {
  switch (type) {
    case PixelType::kByte:
      return "Byte";
    case PixelType::kUInt16:
      return "UInt16";
    case PixelType::kFloat32:
      return "Float32";
  }
  return "Byte";
}

bool TileStoreOptions::IsValid(std::string* error) const {
  std::string problem;
  if (path.empty()) {
    problem = "path is empty: give the store folder";
  } else if (tile_size < 64 || tile_size > 8192 || tile_size % 16 != 0) {
    problem = "tile_size " + std::to_string(tile_size) + " must be a multiple of 16 in [64, 8192]";
  } else if (compression != "ZSTD" && compression != "DEFLATE" && compression != "LZW" &&
             compression != "NONE") {
    problem = "compression '" + compression + "' must be ZSTD, DEFLATE, LZW or NONE";
  } else if (compression_level < 1 || compression_level > 22 ||
             (compression == "DEFLATE" && compression_level > 9)) {
    problem = "compression_level " + std::to_string(compression_level) +
              " out of range (ZSTD 1..22, DEFLATE 1..9)";
  } else if (overview_levels < -1 || overview_levels > 16 ||
             (overview_levels > 0 && tile_size % (1 << overview_levels) != 0)) {
    problem = "overview_levels " + std::to_string(overview_levels) +
              " must be -1 (automatic) or 0..16 with tile_size a multiple of 2^levels";
  } else if (!(overview_interval_s >= 0.0) || !std::isfinite(overview_interval_s)) {
    problem = "overview_interval_s must be >= 0 seconds";
  } else if (!(sync_interval_s >= 0.0) || !std::isfinite(sync_interval_s)) {
    problem = "sync_interval_s must be >= 0 seconds";
  } else if (overview_slice_tiles < 1) {
    problem = "overview_slice_tiles must be at least 1";
  } else if (refresh_slice_tiles < 0) {
    problem = "refresh_slice_tiles must be >= 0 (0: refreshed tiles go with each publish)";
  } else if (refresh_quiet_publishes < 1 || refresh_quiet_publishes > 1000) {
    problem = "refresh_quiet_publishes must be in 1..1000 (1: ready after the next publish)";
  } else if (max_cached_tiles < 4) {
    problem = "max_cached_tiles must be at least 4";
  } else if (writer_nice < 0 || writer_nice > 19) {
    problem = "writer_nice " + std::to_string(writer_nice) + " must be in 0..19";
  }
  if (!problem.empty() && error) *error = problem;
  return problem.empty();
}

namespace {

using Clock = std::chrono::steady_clock;
// CPU time of the calling thread, ms.
double ThreadCpuMs() {
  timespec ts{};
  clock_gettime(CLOCK_THREAD_CPUTIME_ID, &ts);
  return 1e3 * static_cast<double>(ts.tv_sec) + 1e-6 * static_cast<double>(ts.tv_nsec);
}

// Of the calling thread's CPU time, the part spent in the kernel (system time), ms.
double ThreadSystemCpuMs() {
  rusage usage{};
  if (getrusage(RUSAGE_THREAD, &usage) != 0) return 0.0;
  return 1e3 * static_cast<double>(usage.ru_stime.tv_sec) +
         1e-3 * static_cast<double>(usage.ru_stime.tv_usec);
}

// Time the calling thread has waited for a CPU while runnable, ms (Linux: the second field of
// /proc/thread-self/schedstat); 0 where the kernel does not report it. For PublishReport.
double ThreadRunQueueMs() {
  std::FILE* file = std::fopen("/proc/thread-self/schedstat", "r");
  if (!file) return 0.0;
  unsigned long long on_cpu_ns = 0, waiting_ns = 0;
  const int fields = std::fscanf(file, "%llu %llu", &on_cpu_ns, &waiting_ns);
  std::fclose(file);
  return fields == 2 ? 1e-6 * static_cast<double>(waiting_ns) : 0.0;
}

double MsSince(Clock::time_point start) {
  return std::chrono::duration<double, std::milli>(Clock::now() - start).count();
}

// Largest number of overview levels a tile size allows (T must stay divisible by 2^levels).
// The writer's time on a piece of work and its failure, if any ("unexpected failure while
// <what>: ..." for one that is not the store's own Error).
struct TimedWork {
  double busy_ms = 0.0;
  double cpu_ms = 0.0;
  double system_cpu_ms = 0.0;  // Of cpu_ms, in the kernel.
  std::string error;
};
TimedWork RunTimed(const char* what, const std::function<void()>& work) {
  const Clock::time_point start = Clock::now();
  const double cpu_start_ms = ThreadCpuMs();
  const double system_start_ms = ThreadSystemCpuMs();
  TimedWork out;
  try {
    work();
  } catch (const Error& e) {
    out.error = e.what();
  } catch (const std::exception& e) {
    out.error = std::string("unexpected failure while ") + what + ": " + e.what();
  }
  out.busy_ms = MsSince(start);
  out.cpu_ms = ThreadCpuMs() - cpu_start_ms;
  out.system_cpu_ms = ThreadSystemCpuMs() - system_start_ms;
  return out;
}

int MaxLevelsFor(int tile_size) {
  int levels = 0;
  while (levels < 16 && tile_size % (2 << levels) == 0 && (tile_size >> (levels + 1)) >= 8) {
    ++levels;
  }
  return levels;
}

int64_t FloorDiv(int64_t a, int64_t b) { return a >= 0 ? a / b : -((-a + b - 1) / b); }

#if CV_SIMD128
// Eight samples widened to 16 bits, and back.
cv::v_uint16x8 LoadEight(const uint16_t* p) { return cv::v_load(p); }
cv::v_uint16x8 LoadEight(const uchar* p) {
  uint64_t word = 0;  // Copied to an aligned word: v_load_expand reads the bytes as one load.
  std::memcpy(&word, p, sizeof(word));
  return cv::v_load_expand(reinterpret_cast<const uchar*>(&word));
}
void StoreEight(uint16_t* p, const cv::v_uint16x8& v) { cv::v_store(p, v); }
void StoreEight(uchar* p, const cv::v_uint16x8& v) { cv::v_pack_store(p, v); }

// BlendInto's rule for 8 Byte or UInt16 samples from x on, in SSE2 vectors with the scalar loop's
// float operations in its order and its rounding (cvRound: to nearest even, then saturated to
// the type), so the result is identical. Returns whether any sample was painted.
template <typename T>
bool BlendEight(const T* src, const float* w, T* dst, uchar* covered) {
  static_assert(std::is_same_v<T, uint16_t> || std::is_same_v<T, uint8_t>);
  constexpr int kMax = std::numeric_limits<T>::max();
  const cv::v_float32x4 zero = cv::v_setzero_f32(), one = cv::v_setall_f32(1.0f);
  const cv::v_float32x4 w0 = cv::v_load(w), w1 = cv::v_load(w + 4);
  const cv::v_int32x4 paint0 = cv::v_reinterpret_as_s32(w0 > zero);  // Also false for NaN.
  const cv::v_int32x4 paint1 = cv::v_reinterpret_as_s32(w1 > zero);
  if (!cv::v_check_any(paint0) && !cv::v_check_any(paint1)) return false;
  cv::v_uint32x4 s0, s1, d0, d1, c0, c1;
  cv::v_expand(LoadEight(src), s0, s1);
  cv::v_expand(LoadEight(dst), d0, d1);
  cv::v_expand(LoadEight(covered), c0, c1);
  const auto blend = [&](const cv::v_float32x4& wx, const cv::v_uint32x4& s,
                         const cv::v_uint32x4& d, const cv::v_uint32x4& c,
                         const cv::v_int32x4& paint) {
    const cv::v_int32x4 si = cv::v_reinterpret_as_s32(s), di = cv::v_reinterpret_as_s32(d);
    const cv::v_float32x4 mixed = wx * cv::v_cvt_f32(si) + (one - wx) * cv::v_cvt_f32(di);
    const cv::v_int32x4 rounded =
        cv::v_min(cv::v_max(cv::v_round(mixed), cv::v_setzero_s32()), cv::v_setall_s32(kMax));
    const cv::v_int32x4 whole =
        cv::v_reinterpret_as_s32(c == cv::v_setzero_u32()) | cv::v_reinterpret_as_s32(wx >= one);
    return cv::v_select(paint, cv::v_select(whole, si, rounded), di);
  };
  StoreEight(dst, cv::v_pack_u(blend(w0, s0, d0, c0, paint0), blend(w1, s1, d1, c1, paint1)));
  const cv::v_int32x4 full = cv::v_setall_s32(255);
  const cv::v_uint16x8 cov = cv::v_pack_u(cv::v_select(paint0, full, cv::v_reinterpret_as_s32(c0)),
                                          cv::v_select(paint1, full, cv::v_reinterpret_as_s32(c1)));
  cv::v_pack_store(covered, cov);
  return true;
}
#endif

#if defined(__x86_64__)
// BlendEight's rule (and so the scalar loop's: the same float operations in the same order, no
// fused multiply-add, rounding to nearest even) for a row's samples [0, width - width % 8) in
// AVX2 vectors of 8. Returns whether any sample was painted.
template <typename T>
__attribute__((target("avx2"))) bool BlendRowAvx2(const T* src, const float* w, T* dst,
                                                  uchar* covered, int width) {
  static_assert(std::is_same_v<T, uint16_t> || std::is_same_v<T, uint8_t>);
  const __m256 zero = _mm256_setzero_ps(), one = _mm256_set1_ps(1.0f);
  const __m256i zero_i = _mm256_setzero_si256();
  const __m256i max_i = _mm256_set1_epi32(std::numeric_limits<T>::max());
  const __m256i full = _mm256_set1_epi32(255);
  bool painted = false;
  for (int x = 0; x + 8 <= width; x += 8) {
    const __m256 wx = _mm256_loadu_ps(w + x);
    const __m256 paint_f = _mm256_cmp_ps(wx, zero, _CMP_GT_OQ);  // Also false for NaN.
    if (_mm256_movemask_ps(paint_f) == 0) continue;
    painted = true;
    __m256i s, d;
    if constexpr (sizeof(T) == 1) {
      s = _mm256_cvtepu8_epi32(_mm_loadl_epi64(reinterpret_cast<const __m128i*>(src + x)));
      d = _mm256_cvtepu8_epi32(_mm_loadl_epi64(reinterpret_cast<const __m128i*>(dst + x)));
    } else {
      s = _mm256_cvtepu16_epi32(_mm_loadu_si128(reinterpret_cast<const __m128i*>(src + x)));
      d = _mm256_cvtepu16_epi32(_mm_loadu_si128(reinterpret_cast<const __m128i*>(dst + x)));
    }
    const __m256i c =
        _mm256_cvtepu8_epi32(_mm_loadl_epi64(reinterpret_cast<const __m128i*>(covered + x)));
    const __m256 mixed =
        _mm256_add_ps(_mm256_mul_ps(wx, _mm256_cvtepi32_ps(s)),
                      _mm256_mul_ps(_mm256_sub_ps(one, wx), _mm256_cvtepi32_ps(d)));
    const __m256i rounded =
        _mm256_min_epi32(_mm256_max_epi32(_mm256_cvtps_epi32(mixed), zero_i), max_i);
    const __m256i whole = _mm256_or_si256(_mm256_cmpeq_epi32(c, zero_i),
                                          _mm256_castps_si256(_mm256_cmp_ps(wx, one, _CMP_GE_OQ)));
    const __m256i paint = _mm256_castps_si256(paint_f);
    const __m256i value = _mm256_blendv_epi8(d, _mm256_blendv_epi8(rounded, s, whole), paint);
    // To 16 bits (within [0, 65535]), the two 128-bit halves' first 4 words side by side.
    const __m256i words = _mm256_permute4x64_epi64(_mm256_packus_epi32(value, value), 0x08);
    if constexpr (sizeof(T) == 1) {
      const __m128i bytes = _mm_packus_epi16(_mm256_castsi256_si128(words), _mm_setzero_si128());
      _mm_storel_epi64(reinterpret_cast<__m128i*>(dst + x), bytes);
    } else {
      _mm_storeu_si128(reinterpret_cast<__m128i*>(dst + x), _mm256_castsi256_si128(words));
    }
    const __m256i cov = _mm256_blendv_epi8(c, full, paint);
    const __m256i cov_words = _mm256_permute4x64_epi64(_mm256_packus_epi32(cov, cov), 0x08);
    const __m128i cov_bytes =
        _mm_packus_epi16(_mm256_castsi256_si128(cov_words), _mm_setzero_si128());
    _mm_storel_epi64(reinterpret_cast<__m128i*>(covered + x), cov_bytes);
  }
  return painted;
}
#endif

// Whether someone besides the cache holds `m` (a pooled buffer has the pool's reference too).
bool SharedBuffer(const cv::Mat& m, const MatPool& pool) {
  return m.u != nullptr && m.u->refcount > (pool.Owns(m) ? 2 : 1);
}

// Whether BlendInto would look at any sample of `roi`: a weight above zero (NaN is not). Paint
// asks before it touches a tile, so a tile the patch's bounding box reaches but its footprint
// does not (an oblique, rotated frame fills about half of its box) is neither read back from
// disk, created, nor copied.
bool AnyPositiveWeight(const cv::Mat& weight, const cv::Rect& roi) {
  for (int y = 0; y < roi.height; ++y) {
    const float* w = weight.ptr<float>(roi.y + y) + roi.x;
    int x = 0;
#if CV_SIMD128
    const cv::v_float32x4 zero = cv::v_setzero_f32();
    for (; x + 8 <= roi.width; x += 8) {
      if (cv::v_check_any((cv::v_load(w + x) > zero) | (cv::v_load(w + x + 4) > zero))) {
        return true;
      }
    }
#endif
    for (; x < roi.width; ++x) {
      if (w[x] > 0.0f) return true;
    }
  }
  return false;
}

// The blocks of a tile that a paint changed: those where the patch's part (`patch_roi`, landing
// on `tile_roi`) has a weight above zero. A footprint's bounding box covers blocks its
// quadrilateral misses.
store::BlockMask BlocksPainted(const cv::Mat& weight, const cv::Rect& patch_roi,
                               const cv::Rect& tile_roi, int tile_size) {
  const store::BlockMask overlapping = store::BlocksOverlapping(tile_roi, tile_size);
  if (overlapping == store::kAllBlocks || std::popcount(overlapping) <= 1) return overlapping;
  const int block = std::min(store::kBlockSize, tile_size);
  const int across = (tile_size + block - 1) / block;
  const cv::Point shift = patch_roi.tl() - tile_roi.tl();
  store::BlockMask painted = 0;
  for (int bit = 0; bit < 64; ++bit) {
    if (!(overlapping >> bit & 1)) continue;
    const cv::Rect part =
        cv::Rect((bit % across) * block, (bit / across) * block, block, block) & tile_roi;
    if (AnyPositiveWeight(weight, part + shift)) painted |= store::BlockMask{1} << bit;
  }
  return painted;
}

// The layouts of the tile files the writer wrote last (the most recent `capacity`), by level and
// tile, so that a tile written again copies its unchanged blocks from its file.
class LayoutCache {
 public:
  using Key = std::tuple<int, int64_t, int64_t>;
  explicit LayoutCache(size_t capacity) : capacity_(capacity) {}
  const store::TileFileLayout* Find(int level, const TileIndex& tile) const {
    const auto it = layouts_.find({level, tile.first, tile.second});
    return it == layouts_.end() ? nullptr : &it->second.first;
  }
  void Put(int level, const TileIndex& tile, store::TileFileLayout layout) {
    const Key key{level, tile.first, tile.second};
    const auto it = layouts_.find(key);
    if (layout.offsets.empty()) {  // Not written directly: nothing to copy from next time.
      if (it != layouts_.end()) {
        order_.erase(it->second.second);
        layouts_.erase(it);
      }
      return;
    }
    if (it != layouts_.end()) {
      it->second.first = std::move(layout);
      order_.splice(order_.end(), order_, it->second.second);
      return;
    }
    order_.push_back(key);
    layouts_.emplace(key, std::make_pair(std::move(layout), std::prev(order_.end())));
    while (layouts_.size() > capacity_) {
      layouts_.erase(order_.front());
      order_.pop_front();
    }
  }

 private:
  size_t capacity_;
  std::list<Key> order_;  // Least recently written first.
  std::map<Key, std::pair<store::TileFileLayout, std::list<Key>::iterator>> layouts_;
};

template <typename T>
bool BlendInto(const cv::Mat& image, const cv::Mat& weight, const cv::Rect& patch_roi,
               cv::Mat* data, cv::Mat* alpha, const cv::Rect& tile_roi) {
  bool painted = false;
#if defined(__x86_64__)
  const bool avx2 = simd::Avx2();  // 8 samples per vector of 8 floats instead of two of 4.
#endif
  for (int y = 0; y < patch_roi.height; ++y) {
    const T* src = image.ptr<T>(patch_roi.y + y) + patch_roi.x;
    const float* w = weight.ptr<float>(patch_roi.y + y) + patch_roi.x;
    T* dst = data->ptr<T>(tile_roi.y + y) + tile_roi.x;
    uchar* covered = alpha->ptr<uchar>(tile_roi.y + y) + tile_roi.x;
    int x = 0;
#if defined(__x86_64__)
    if constexpr (std::is_same_v<T, uint16_t> || std::is_same_v<T, uint8_t>) {
      if (avx2) {
        painted |= BlendRowAvx2(src, w, dst, covered, patch_roi.width);
        x = patch_roi.width - patch_roi.width % 8;
      }
    }
#endif
#if CV_SIMD128
    if constexpr (std::is_same_v<T, uint16_t> || std::is_same_v<T, uint8_t>) {
      for (; x + 8 <= patch_roi.width; x += 8) {
        painted |= BlendEight(src + x, w + x, dst + x, covered + x);
      }
    }
#endif
    for (; x < patch_roi.width; ++x) {
      const float wx = w[x];
      if (!(wx > 0.0f)) continue;  // Also skips NaN weights.
      if constexpr (std::is_floating_point_v<T>) {
        if (!std::isfinite(src[x])) continue;
      }
      painted = true;
      if (covered[x] == 0 || wx >= 1.0f) {
        dst[x] = src[x];
        covered[x] = 255;
      } else {
        const float value =
            wx * static_cast<float>(src[x]) + (1.0f - wx) * static_cast<float>(dst[x]);
        dst[x] = cv::saturate_cast<T>(value);
      }
    }
  }
  return painted;
}

// Each frame index's time, in blocks of 4096 indices (8 bytes a frame, sparse indices cost a
// block each): what the manifest's frame count and time range need, without the records.
class FrameTimes {
 public:
  // Sets the time of `index`; returns the one it had, if any.
  std::optional<double> Set(int64_t index, double time_s) {
    Block& block = blocks_[index / kBlock];
    const size_t at = static_cast<size_t>(index % kBlock);
    std::optional<double> old;
    if (block.present[at]) {
      old = block.time_s[at];
    } else {
      block.present[at] = true;
      ++count_;
    }
    block.time_s[at] = time_s;
    return old;
  }
  int64_t count() const { return count_; }
  template <class Visit>
  void ForEach(Visit visit) const {
    for (const auto& [key, block] : blocks_) {
      for (size_t at = 0; at < kBlock; ++at) {
        if (block.present[at]) visit(block.time_s[at]);
      }
    }
  }

 private:
  static constexpr int64_t kBlock = 4096;
  struct Block {
    std::array<double, kBlock> time_s{};
    std::bitset<kBlock> present;
  };
  std::unordered_map<int64_t, Block> blocks_;
  int64_t count_ = 0;
};

bool SameRecord(const FrameRecord& a, const FrameRecord& b) {
  return a.index == b.index && a.time_s == b.time_s && a.footprint_m == b.footprint_m &&
         a.pos_only == b.pos_only && a.residual_px == b.residual_px && a.inliers == b.inliers &&
         a.status == b.status;
}

}  // namespace

struct TileStore::Impl {
  TileStoreOptions options;
  StoreGeoreference georef;
  PixelType type = PixelType::kUInt16;
  fs::path root;
  bool read_only = false;
  std::string created_utc;
  int max_levels = 0;

  // --- Shared state, under `mutex`.
  mutable std::mutex mutex;
  std::condition_variable changed;  // Any of: request, publish done, tile written.
  struct CachedTile {
    TileImage image;
    bool dirty = false;  // Painted since its last snapshot by the writer.
    // Painted since its last snapshot by refreshes only, on disk already: a refresh slice or a
    // publish writes it (never both dirty and refreshed).
    bool refreshed = false;
    uint64_t paint_epoch = 0;  // publish_epoch when last painted.
    bool writing = false;      // Snapshot taken, file not yet renamed into place: keep in memory.
    // Buffers given to a writer's snapshot: copy before painting while the writer still holds
    // them (it lets go, under the lock, once the tile is on disk and halved for the overviews).
    bool shared = false;
    uint64_t last_use = 0;
    // Blocks painted since the writer's last snapshot (a write copies the others from the file).
    store::BlockMask changed_blocks = 0;
  };
  std::map<TileIndex, CachedTile> cache;
  // Tile buffers (mat_pool.h), made at first use when the tile size and type are settled:
  // the cache, the painters' copies, the writer's backlog and halves, the overview cache.
  std::once_flag pools_made;
  std::unique_ptr<store::TilePools> pools;
  store::TilePools& Pools() {
    std::call_once(pools_made, [this] {
      pools = std::make_unique<store::TilePools>(options.tile_size, type,
                                                 6 * options.max_cached_tiles + 32);
    });
    return *pools;
  }
  size_t dirty_count = 0;
  size_t refreshed_count = 0;  // Tiles with `refreshed` set.
  uint64_t publish_epoch = 0;  // Snapshots taken by publishes so far.
  // A refresh slice replaced tiles since the last publish's snapshot: the next publish bumps the
  // generation even with nothing else new, so readers that cache blocks per generation (the
  // IRMOSAIC plug-in) read them again.
  bool replaced_since_publish = false;
  uint64_t use_clock = 0;
  store::LevelTiles
      level0_on_disk;  // Level-0 tiles whose file exists (written or listed at resume).
  // Frame records put and not yet in frames.gpkg (or being written to it): a flight's records
  // live in frames.gpkg, where FrameRecords() reads them, not in memory (an hour: ~90,000).
  std::map<int64_t, FrameRecord> frames;
  FrameTimes frame_times;  // Every record's time, for the manifest's count and time range.
  // Time range of the records, kept as records come (a publish no longer walks every record of
  // the flight under the lock: ~90,000 in an hour); stale: recomputed at the next publish.
  std::pair<double, double> frames_time{kNoTime, -kNoTime};
  bool frames_time_stale = true;
  static constexpr double kNoTime = std::numeric_limits<double>::infinity();
  void WidenFramesTime(double time_s) {
    frames_time = {std::min(frames_time.first, time_s), std::max(frames_time.second, time_s)};
  }
  std::vector<FrameRecord> frames_changed;
  std::string application_json;
  bool application_dirty = false;
  std::optional<std::array<int64_t, 4>> planned_bounds_px;  // SetPlannedBoundsPx.
  int64_t requested_generation = 0;
  int64_t started_generation = 0;  // Generation the writer is working on (or last worked on).
  int64_t published_generation = 0;
  int64_t failed_generation = 0;  // Last generation whose publish failed.
  std::string last_error;
  bool stop = false;
  // Close() asked for the last publish: nothing may be deferred. Atomic: an overview slice reads
  // it with the mutex released (FinishOverviewCycle).
  std::atomic<bool> closing{false};
  bool secondary_owed = false;  // Overviews or frames.gpkg were deferred by a publish.
  // The closing publish found frames.gpkg locked past its wait: Close() says so.
  bool frames_gpkg_locked_at_close = false;
  bool closed = false;  // Writer joined: nothing more will be published.
  std::map<int64_t, Clock::time_point> request_time_of;
  std::deque<std::pair<int64_t, Clock::time_point>> published_at;  // The last 4096 publishes.
  int64_t published_at_dropped_through = 0;  // Newest generation dropped from published_at.
  std::vector<double> publish_latencies_ms;
  Stats stats;

  // --- Writer-thread state (only the writer touches these after Open).
  store::Manifest manifest;   // The last published manifest.
  TileSet propagate_pending;  // Level-0 tiles written by a failed publish: overviews owe them.
  // Level-0 tiles written while overviews were deferred (their latest images, halved: what
  // level 1 takes of them, a quarter of the memory), and when the overviews and frames.gpkg
  // were last brought up to date (none yet: the first publish brings them; a default time point
  // is the clock's epoch, the machine's boot, so a store opened within overview_interval_s of
  // boot skipped its first update).
  std::map<TileIndex, TileImage> overview_owed;
  std::optional<Clock::time_point> last_secondary;
  // The overview update under way (cycle_levels >= 0): cycle_owed[L] holds the changed tiles of
  // level L - 1, halved, that level L still has to take (an empty image: read from disk when its
  // turn comes); build_whole[L]: level L is new, built from every tile of level L - 1 once the
  // levels below are done. Paused after a failure until the next publish.
  int cycle_levels = -1;
  std::vector<std::map<TileIndex, TileImage>> cycle_owed;
  TileSet cycle_level0;  // The level-0 tiles the update under way brings into the overviews.
  // What the index lists as owed (manifest overviews_owed): the tiles waiting for the next
  // overview update and those of the update under way.
  std::vector<TileIndex> OverviewsOwed() const {
    TileSet owed = cycle_level0;
    for (const auto& [index, half] : overview_owed) owed.insert(index);
    return {owed.begin(), owed.end()};
  }
  std::vector<bool> build_whole;
  bool cycle_paused = false;
  bool slice_turn = false;    // The writer published last: a slice goes before the next publish.
  bool refresh_turn = false;  // ... and a refresh slice.
  // Slices run since the last publish, for its PublishReport (on_publish).
  int slices_refresh = 0, slices_overview = 0;
  double slices_ms = 0.0;
  bool refresh_paused = false;  // A refresh slice failed: none until the next publish.
  // A refreshed tile is written by a slice once refresh_quiet_publishes publishes passed since
  // it was last painted, so that a tile the re-renders keep painting is written no more often
  // than that.
  bool RefreshReady(const CachedTile& tile) const {
    return tile.refreshed &&
           tile.paint_epoch + static_cast<uint64_t>(options.refresh_quiet_publishes) <=
               publish_epoch;
  }
  bool RefreshRunnable() const {
    if (refreshed_count == 0 || refresh_paused || options.refresh_slice_tiles == 0) return false;
    for (const auto& [index, tile] : cache) {
      if (RefreshReady(tile)) return true;
    }
    return false;
  }
  bool index_owed = false;  // A slice listed new overview tiles that no index names yet.
  bool qlr_owed = false;    // A slice moved the display range the .qlr files hold.
  size_t CycleOwedCount() const {
    size_t n = 0;
    for (const auto& level : cycle_owed) n += level.size();
    return n;
  }
  bool CycleRunnable() const { return cycle_levels >= 0 && !cycle_paused; }
  std::optional<Clock::time_point> last_clean;  // Last CleanStaleFiles (stale overview VRTs).
  static constexpr std::chrono::seconds kCleanInterval{60};
  std::map<std::pair<int, TileIndex>, TileImage> overview_cache;
  std::list<std::pair<int, TileIndex>> overview_lru;
  std::thread writer;
  // The file system flusher (sync_interval_s): its own lock, so a flush stuck behind a slow disk
  // holds up nothing but Close.
  std::thread syncer;
  std::mutex sync_mutex;
  std::condition_variable sync_wake;
  bool sync_stop = false;
  std::atomic<int64_t> syncs{0};
  void SyncLoop();

  fs::path PathOf(int level, const TileIndex& tile) const {
    return root / store::TileRelativePath(level, tile);
  }
  store::TileWriteSettings WriteSettings() const {
    return {type, options.compression, options.compression_level, georef.crs_wkt, options.durable};
  }

  CachedTile& TileLocked(const TileIndex& index, std::unique_lock<std::mutex>& lock);
  void EvictLocked();
  void WriterLoop();
  void PublishOnce(int64_t generation, std::unique_lock<std::mutex>& lock);
  // Overview updates. Start: the tiles owed so far join the update (levels as `target`'s level
  // 0 asks). Step: one slice, at most max_parents tiles of the lowest level owing any (a new
  // level whole), listed in `target`; true when nothing is left. Slice: a step between publishes
  // (lock held on entry and exit), the index rewritten when the update ends.
  void StartOverviewCycle(store::Manifest* target);
  bool OverviewStep(store::Manifest* target, size_t max_parents, int64_t* bytes, int64_t* tiles,
                    std::vector<TileImage>* top);
  void FinishOverviewCycle(const store::Manifest& current);
  void OverviewSlice(std::unique_lock<std::mutex>& lock);
  // Writes up to refresh_slice_tiles refreshed tiles in place (lock held on entry and exit).
  void RefreshSlice(std::unique_lock<std::mutex>& lock);
  // Writes a level-0 tile of a snapshot (lock not held on entry), then under the lock notes it
  // on disk and lets its cached tile go; returns the file's size.
  int64_t WriteLevel0Tile(const TileIndex& index, const TileImage& image, store::BlockMask changed,
                          std::unique_lock<std::mutex>& lock);
  // Writes a tile of any level (writer thread), copying the blocks outside `changed` from its
  // file when the writer knows that file's layout; notes the new file's layout.
  int64_t WriteTile(int level, const TileIndex& index, const TileImage& image,
                    store::BlockMask changed_blocks);
  std::unique_ptr<LayoutCache> layouts;  // Writer thread only; made at Open.
  // Changed blocks of a publish's or a refresh slice's snapshot, by tile.
  std::map<TileIndex, store::BlockMask> snapshot_changed;
  // Widens m's display range by the covered values of `top` (the highest level's tiles); true
  // if it moved enough to rewrite the .qlr files.
  static bool WidenDisplayRange(store::Manifest* m, const std::vector<const TileImage*>& top);
  // Drops the writer's references to snapshot images (lock not held on entry) under the lock.
  // The snapshot shares its buffers with the cache: Paint copies a shared buffer under the lock
  // and drops its own reference inside OpenCV (reference count in uninstrumented code, with
  // acquire-release order), so the writer may free a buffer after a painter's read. That order
  // is real; dropping under the lock makes it visible to ThreadSanitizer too (a free outside
  // the lock was reported as a race), at the cost of a lock per level per publish.
  static void ReleaseSnapshot(std::map<TileIndex, TileImage>* images,
                              std::unique_lock<std::mutex>& lock) {
    lock.lock();
    images->clear();
    lock.unlock();
  }
  // Writes the level-`level` tiles over `children`: changed tiles of the level below, halved.
  std::map<TileIndex, TileImage> UpdateOverviewLevel(int level,
                                                     const std::map<TileIndex, TileImage>& children,
                                                     int64_t* bytes, int64_t* tiles);
  TileImage OverviewTile(int level, const TileIndex& tile);
  void RememberOverview(int level, const TileIndex& tile, const TileImage& image);
  int64_t overview_reads = 0;  // Writer thread only (Stats::overview_reads).
  int LevelsFor(const store::LevelTiles& level0) const;
  void WriteIndex(store::Manifest* next, int64_t generation);
  // Writer thread only: tiles per block as each block VRT was last written (per level), and
  // the index figures of the publishes so far.
  std::vector<std::map<store::BlockIndex, int64_t>> block_tile_counts;
  // Writer thread only: each overview VRT as this process last wrote it (per level).
  struct LevelVrtState {
    std::string relative;
    std::vector<store::BlockIndex> blocks;
  };
  std::vector<LevelVrtState> level_vrts_written;
  int64_t index_bytes = 0;
  double index_ms = 0.0;
  void WriteQlr(const store::Manifest& m) {
    double lo = m.display_lo, hi = m.display_hi;
    if (hi <= lo) {  // Nothing painted yet: the type's range.
      lo = 0.0;
      hi = type == PixelType::kByte ? 255.0 : type == PixelType::kUInt16 ? 65535.0 : 100.0;
    }
    store::WriteFileAtomic(root / (options.layer_name + ".qlr"),
                           store::BuildQlr(options.layer_name, georef.crs_wkt, lo, hi),
                           options.durable);
    store::WriteFileAtomic(root / (options.layer_name + "_live.qlr"),
                           store::BuildQlr(options.layer_name, georef.crs_wkt, lo, hi, true),
                           options.durable);
  }
  void CleanStaleFiles(const store::Manifest& current);
};

TileStore::Impl::CachedTile& TileStore::Impl::TileLocked(const TileIndex& index,
                                                         std::unique_lock<std::mutex>& lock) {
  auto it = cache.find(index);
  if (it == cache.end()) {
    CachedTile tile;
    if (level0_on_disk.count(index)) {
      // Reload outside the lock so the writer is not held up by this read.
      lock.unlock();
      TileImage image = store::ReadTile(PathOf(0, index), options.tile_size, type, &Pools());
      lock.lock();
      ++stats.tile_reloads;
      it = cache.find(index);  // Another painter may have loaded it meanwhile.
      if (it != cache.end()) return it->second;
      tile.image = std::move(image);
    } else {
      tile.image = store::EmptyTile(&Pools());
    }
    it = cache.emplace(index, std::move(tile)).first;
  }
  it->second.last_use = ++use_clock;
  return it->second;
}

void TileStore::Impl::EvictLocked() {
  while (cache.size() > options.max_cached_tiles) {
    auto victim = cache.end();
    for (auto it = cache.begin(); it != cache.end(); ++it) {
      if (it->second.dirty || it->second.refreshed || it->second.writing) continue;
      if (victim == cache.end() || it->second.last_use < victim->second.last_use) victim = it;
    }
    if (victim == cache.end()) return;  // All wait for the writer.
    cache.erase(victim);
  }
}

int TileStore::Impl::LevelsFor(const store::LevelTiles& level0) const {
  if (options.overview_levels >= 0) return options.overview_levels;
  const store::TileBounds b = level0.bounds();
  const int64_t span = std::max(b.row1 - b.row0, b.col1 - b.col0);
  int levels = 0;
  while ((int64_t{1} << levels) < span && levels < max_levels) ++levels;
  return levels;
}

void TileStore::Impl::RememberOverview(int level, const TileIndex& tile, const TileImage& image) {
  // First in, first out. Least recently used (a hit moved to the back) was measured worse over
  // a sweeping flight: 1206-1217 overview tiles read back from disk in 600 frames against
  // 913-922 (docs/benchmarks.md, "Session 8").
  const auto key = std::make_pair(level, tile);
  if (!overview_cache.count(key)) overview_lru.push_back(key);
  overview_cache[key] = image;
  while (overview_cache.size() > options.max_cached_tiles) {
    overview_cache.erase(overview_lru.front());
    overview_lru.pop_front();
  }
}

TileImage TileStore::Impl::OverviewTile(int level, const TileIndex& tile) {
  auto it = overview_cache.find({level, tile});
  if (it != overview_cache.end()) return it->second;
  // A file on disk always holds that tile's last complete write, published or about to be.
  const fs::path path = PathOf(level, tile);
  if (fs::exists(path)) {
    ++overview_reads;
    return store::ReadTile(path, options.tile_size, type, &Pools());
  }
  return store::EmptyTile(&Pools());
}

std::map<TileIndex, TileImage> TileStore::Impl::UpdateOverviewLevel(
    int level, const std::map<TileIndex, TileImage>& children, int64_t* bytes, int64_t* tiles) {
  // Group changed children by parent; a parent on disk already holds its other quadrants.
  std::map<TileIndex, std::vector<const std::pair<const TileIndex, TileImage>*>> by_parent;
  for (const auto& child : children) {
    by_parent[{FloorDiv(child.first.first, 2), FloorDiv(child.first.second, 2)}].push_back(&child);
  }
  const int half = options.tile_size / 2;
  std::map<TileIndex, TileImage> written;
  for (const auto& [parent, kids] : by_parent) {
    TileImage image = OverviewTile(level, parent);
    store::BlockMask quadrants = 0;  // Of these children: the file has the others.
    for (const auto* kid : kids) {
      const TileImage& small = kid->second;  // Halved by the caller.
      const int qy = static_cast<int>(kid->first.first - 2 * parent.first);
      const int qx = static_cast<int>(kid->first.second - 2 * parent.second);
      const cv::Rect quadrant(qx * half, qy * half, half, half);
      small.data.copyTo(image.data(quadrant));
      small.alpha.copyTo(image.alpha(quadrant));
      quadrants |= store::BlocksOverlapping(quadrant, options.tile_size);
    }
    fs::create_directories(root / ("tiles/" + std::to_string(level)));
    *bytes += WriteTile(level, parent, image, quadrants);
    ++*tiles;
    RememberOverview(level, parent, image);
    written.emplace(parent, std::move(image));
  }
  return written;
}

void TileStore::Impl::WriteIndex(store::Manifest* next, int64_t generation) {
  const Clock::time_point start = Clock::now();
  store::Manifest& m = *next;
  const int levels = static_cast<int>(m.levels.size()) - 1;
  m.generation = generation;
  m.published_utc = store::UtcNow();
  m.overviews_owed = OverviewsOwed();
  m.overview_vrts.clear();
  // Grown in steps (store::VrtBounds) so that the overview VRTs, named by it, stay the same
  // file over many publishes; export crops to the painted tiles.
  const store::TileBounds bounds = store::VrtBounds(m.levels[0].bounds());
  // Block VRTs first (the level VRTs name them): only those that gained tiles since this
  // process last wrote them; after an open, each once (a store of an older layout has none).
  block_tile_counts.resize(m.levels.size());
  for (int level = 0; level <= levels; ++level) {
    for (const auto& [block, rows] : m.levels[level].blocks()) {
      const int64_t count = store::TilesIn(rows);
      auto& written = block_tile_counts[level];
      const auto it = written.find(block);
      if (it != written.end() && it->second == count) continue;
      const std::string xml = store::BuildBlockVrt(m, level, block);
      store::WriteFileAtomic(root / ("tiles/" + std::to_string(level)) / store::BlockVrtName(block),
                             xml, options.durable);
      index_bytes += static_cast<int64_t>(xml.size());
      written[block] = count;
    }
  }
  level_vrts_written.resize(m.levels.size());
  for (int level = 0; level <= levels; ++level) {
    // Named by the ground it spans, not by generation: a later generation with the same extent
    // replaces the file (more sources, same geometry), so a reader holding an older mosaic.vrt
    // that opens it late (GDAL opens sources and overviews at the first read that needs them)
    // still finds a file of the geometry it expects.
    const std::string relative = store::LevelVrtPath(level, bounds);
    if (level == 0) {
      m.level0_vrt = relative;
    } else {
      m.overview_vrts.push_back(relative);
    }
    // Its text depends on the extent (in its name) and the level's blocks only: rewritten when
    // these changed since this process last wrote it, else only its time is renewed (stale
    // level VRTs go an hour after they were last current: CleanStaleFiles).
    std::vector<store::BlockIndex> blocks;
    blocks.reserve(m.levels[level].blocks().size());
    for (const auto& entry : m.levels[level].blocks()) blocks.push_back(entry.first);
    LevelVrtState& last = level_vrts_written[level];
    if (last.relative == relative && last.blocks == blocks) {
      std::error_code error;
      fs::last_write_time(root / relative, fs::file_time_type::clock::now(), error);
      if (!error) continue;  // Else (the file is gone) it is written again.
    }
    const std::string xml = store::BuildLevelVrt(m, level, bounds);
    store::WriteFileAtomic(root / relative, xml, options.durable);
    index_bytes += static_cast<int64_t>(xml.size());
    last.relative = relative;
    last.blocks = std::move(blocks);
  }
  // mosaic.vrt, the one VRT written at every publish (it carries the generation): a few KiB.
  const std::string vrt = store::BuildMosaicVrt(m, bounds, m.level0_vrt, m.overview_vrts);
  store::WriteFileAtomic(root / "mosaic.vrt", vrt, options.durable);
  const std::string json = store::ManifestToJson(m);
  store::WriteFileAtomic(root / "manifest.json", json, options.durable);
  index_bytes += static_cast<int64_t>(vrt.size() + json.size());
  index_ms += MsSince(start);
}

void TileStore::Impl::CleanStaleFiles(const store::Manifest& current) {
  // Overview VRTs of extents the mosaic has outgrown: GDAL opens a VRT's overviews lazily, when
  // a zoomed-out read first needs them, so a reader holding an older mosaic.vrt may still ask
  // for them; they go after an hour (the mosaic outgrows an extent a few hundred times per
  // flight, so few files wait). Each call lists every overview tile's folder, so PublishOnce
  // calls it once a minute (kCleanInterval) and when closing, not with every overview update.
  std::set<std::string> in_use(current.overview_vrts.begin(), current.overview_vrts.end());
  in_use.insert(current.level0_vrt);
  const auto now = fs::file_time_type::clock::now();
  std::error_code error;
  for (const auto& dir : fs::directory_iterator(root / "tiles", error)) {
    const std::string top = dir.path().filename().string();
    if (top.rfind("level0_", 0) == 0 && top.size() > 4 &&
        top.compare(top.size() - 4, 4, ".vrt") == 0) {  // Level 0's VRTs, in tiles/ itself.
      const auto modified = fs::last_write_time(dir.path(), error);
      if (!error && !in_use.count("tiles/" + top) && now - modified > std::chrono::hours(1)) {
        fs::remove(dir.path(), error);
      }
      continue;
    }
    if (top == "0" || !dir.is_directory(error)) continue;  // Level 0 holds tiles only.
    for (const auto& entry : fs::directory_iterator(dir.path(), error)) {
      const std::string name = entry.path().filename().string();
      if (name.rfind("overview_", 0) != 0 || name.size() < 4 ||
          name.compare(name.size() - 4, 4, ".vrt") != 0) {
        continue;
      }
      // As the manifest names them; built, not asked of the file system (fs::relative resolves
      // every component of both paths: a quarter of the writer's CPU an hour into a flight).
      const std::string relative = "tiles/" + dir.path().filename().string() + "/" + name;
      const auto modified = fs::last_write_time(entry.path(), error);
      if (!error && !in_use.count(relative) && now - modified > std::chrono::hours(1)) {
        fs::remove(entry.path(), error);
      }
    }
  }
}

bool TileStore::Impl::WidenDisplayRange(store::Manifest* m,
                                        const std::vector<const TileImage*>& top) {
  double lo = 0, hi = 0;
  if (!store::CoveredPercentiles(top, &lo, &hi)) return false;
  if (m->display_hi > m->display_lo) {
    lo = std::min(lo, m->display_lo);
    hi = std::max(hi, m->display_hi);
  }
  const double span = std::max(hi - lo, 1e-6);
  const bool changed =
      std::abs(lo - m->display_lo) > 0.02 * span || std::abs(hi - m->display_hi) > 0.02 * span;
  m->display_lo = lo;
  m->display_hi = hi;
  return changed;
}

void TileStore::Impl::StartOverviewCycle(store::Manifest* target) {
  const int levels = LevelsFor(target->levels[0]);
  const int existing = static_cast<int>(target->levels.size()) - 1;
  if (target->levels.size() > static_cast<size_t>(levels) + 1) {
    target->levels.resize(levels + 1);  // Fewer levels than before (a resume with other options).
  }
  if (cycle_levels < 0) {
    cycle_owed.clear();
    build_whole.clear();
  }
  cycle_owed.resize(levels + 1);
  build_whole.resize(levels + 1, false);
  for (int level = existing + 1; level <= levels; ++level) build_whole[level] = true;
  cycle_levels = levels;
  if (levels >= 1) {
    for (auto& [index, half] : overview_owed) {
      cycle_level0.insert(index);
      cycle_owed[1][index] = std::move(half);
    }
  }
  overview_owed.clear();
}

bool TileStore::Impl::OverviewStep(store::Manifest* target, size_t max_parents, int64_t* bytes,
                                   int64_t* tiles, std::vector<TileImage>* top) {
  for (int level = 1; level <= cycle_levels; ++level) {
    std::map<TileIndex, TileImage>& owed = cycle_owed[level];
    bool whole = false;
    if (build_whole[level]) {
      // A level the extent just gained, built in one step so that it appears complete. In a
      // flight that is when the extent passes a power of two tiles: the level below spans at
      // most 3 x 3 tiles then. The levels below are done: this is the lowest level owing.
      for (const TileIndex& tile : target->levels[level - 1].tiles())
        owed.emplace(tile, TileImage{});
      build_whole[level] = false;
      whole = true;
    }
    if (owed.empty()) continue;
    std::map<TileIndex, std::vector<TileIndex>> by_parent;
    for (const auto& [child, half] : owed) {
      by_parent[{FloorDiv(child.first, 2), FloorDiv(child.second, 2)}].push_back(child);
    }
    std::map<TileIndex, TileImage> children;
    size_t parents = 0;
    for (const auto& [parent, kids] : by_parent) {
      if (!whole && parents == max_parents) break;
      ++parents;
      for (const TileIndex& child : kids) {
        TileImage half = owed.at(child);
        if (half.empty()) {  // Owed without its image: the file holds it.
          half = store::HalveTile(
              level == 1 ? store::ReadTile(PathOf(0, child), options.tile_size, type, &Pools())
                         : OverviewTile(level - 1, child),
              &Pools());
        }
        children.emplace(child, std::move(half));
      }
    }
    std::map<TileIndex, TileImage> written = UpdateOverviewLevel(level, children, bytes, tiles);
    if (target->levels.size() <= static_cast<size_t>(level)) target->levels.resize(level + 1);
    for (auto& [parent, image] : written) {
      index_owed = target->levels[level].insert(parent) || index_owed;
      if (level < cycle_levels) {
        cycle_owed[level + 1][parent] = store::HalveTile(image, &Pools());
      } else {
        top->push_back(std::move(image));
      }
    }
    for (const auto& [child, half] : children) owed.erase(child);
    break;
  }
  for (int level = 1; level <= cycle_levels; ++level) {
    if (!cycle_owed[level].empty() || build_whole[level]) return false;
  }
  return true;
}

void TileStore::Impl::FinishOverviewCycle(const store::Manifest& current) {
  cycle_levels = -1;
  cycle_owed.clear();
  cycle_level0.clear();
  build_whole.clear();
  if (closing || !last_clean || Clock::now() - *last_clean >= kCleanInterval) {
    CleanStaleFiles(current);
    last_clean = Clock::now();
  }
  last_secondary = Clock::now();
}

void TileStore::Impl::OverviewSlice(std::unique_lock<std::mutex>& lock) {
  lock.unlock();
  int64_t bytes = 0, tiles = 0;
  const TimedWork work = RunTimed("updating the overviews", [&] {
    std::vector<TileImage> top;
    const bool done = OverviewStep(&manifest, static_cast<size_t>(options.overview_slice_tiles),
                                   &bytes, &tiles, &top);
    std::vector<const TileImage*> top_images;
    for (const TileImage& image : top) top_images.push_back(&image);
    qlr_owed = WidenDisplayRange(&manifest, top_images) || qlr_owed;
    if (done) {
      // New overview tiles become visible with the index; tiles already listed were replaced
      // in place. The generation stays: no level-0 tile changed.
      cycle_level0.clear();  // Done: the index lists only what waits for the next update.
      if (index_owed) WriteIndex(&manifest, manifest.generation);
      index_owed = false;
      if (qlr_owed) WriteQlr(manifest);
      qlr_owed = false;
      FinishOverviewCycle(manifest);
    }
  });
  lock.lock();
  // A failed slice (a full disk) keeps what it owed and waits for the next publish, which
  // reports the condition if it persists, instead of retrying in a loop.
  if (!work.error.empty()) cycle_paused = true;
  ++stats.overview_slices;
  ++slices_overview;
  slices_ms += work.busy_ms;
  stats.writer_busy_ms += work.busy_ms;
  stats.writer_cpu_ms += work.cpu_ms;
  stats.writer_system_cpu_ms += work.system_cpu_ms;
  stats.tiles_written += tiles;
  stats.blocks_copied = store::BlocksCopied();
  stats.blocks_encoded = store::BlocksEncoded();
  stats.overview_tiles_written += tiles;
  stats.bytes_written += bytes;
  stats.overview_reads = overview_reads;
  stats.index_ms_total = index_ms;
  stats.index_bytes_total = index_bytes;
  stats.overview_owed_tiles = overview_owed.size() + CycleOwedCount();
  stats.overviews_pending = cycle_levels >= 0 || !overview_owed.empty();
  changed.notify_all();
}

int64_t TileStore::Impl::WriteTile(int level, const TileIndex& index, const TileImage& image,
                                   store::BlockMask changed_blocks) {
  double gt[6];
  store::TileGeoTransform(georef.gsd_m, options.tile_size, level, index, gt);
  const store::TileReuse reuse{layouts->Find(level, index), changed_blocks};
  store::TileFileLayout layout;
  const int64_t bytes =
      store::WriteTileAtomic(PathOf(level, index), image, gt, WriteSettings(), &reuse, &layout);
  layouts->Put(level, index, std::move(layout));
  return bytes;
}

int64_t TileStore::Impl::WriteLevel0Tile(const TileIndex& index, const TileImage& image,
                                         store::BlockMask changed_blocks,
                                         std::unique_lock<std::mutex>& lock) {
  const int64_t bytes = WriteTile(0, index, image, changed_blocks);
  lock.lock();
  level0_on_disk.insert(index);
  auto it = cache.find(index);
  if (it != cache.end()) it->second.writing = false;
  changed.notify_all();
  lock.unlock();
  return bytes;
}

void TileStore::Impl::RefreshSlice(std::unique_lock<std::mutex>& lock) {
  // The tiles painted least recently first: the sweep has left them.
  std::vector<std::pair<uint64_t, TileIndex>> order;
  for (const auto& [index, tile] : cache) {
    if (RefreshReady(tile)) order.emplace_back(tile.last_use, index);
  }
  const size_t n = std::min(order.size(), static_cast<size_t>(options.refresh_slice_tiles));
  std::partial_sort(order.begin(), order.begin() + static_cast<std::ptrdiff_t>(n), order.end());
  std::map<TileIndex, TileImage> images;
  snapshot_changed.clear();
  for (size_t k = 0; k < n; ++k) {
    CachedTile& tile = cache.at(order[k].second);
    images[order[k].second] = tile.image;  // Shared as a publish's snapshot is.
    snapshot_changed[order[k].second] = std::exchange(tile.changed_blocks, 0);
    tile.shared = true;
    tile.writing = true;
    tile.refreshed = false;
    --refreshed_count;
  }
  lock.unlock();
  int64_t bytes = 0, tiles = 0;
  const TimedWork work = RunTimed("writing refreshed tiles", [&] {
    // Listed tiles replaced in place, as overview tiles are: no index to write, the generation
    // stays. Their overviews take them with the next update.
    for (const auto& [index, image] : images) {
      bytes += WriteLevel0Tile(index, image, snapshot_changed.at(index), lock);
      ++tiles;
      overview_owed[index] = store::HalveTile(image, &Pools());
    }
  });
  ReleaseSnapshot(&images, lock);
  lock.lock();
  if (!work.error.empty()) {
    // What was not written waits again; the next publish reports a condition that persists.
    refresh_paused = true;
    for (auto& [index, tile] : cache) {
      if (!tile.writing) continue;
      tile.writing = false;
      tile.changed_blocks = store::kAllBlocks;  // Its file may be either: encode it all.
      if (!tile.dirty && !tile.refreshed) {
        tile.refreshed = true;
        ++refreshed_count;
      }
    }
  }
  ++stats.refresh_slices;
  ++slices_refresh;
  slices_ms += work.busy_ms;
  stats.refresh_tiles_written += tiles;
  replaced_since_publish = replaced_since_publish || tiles > 0;
  stats.writer_busy_ms += work.busy_ms;
  stats.writer_cpu_ms += work.cpu_ms;
  stats.writer_system_cpu_ms += work.system_cpu_ms;
  stats.tiles_written += tiles;
  stats.blocks_copied = store::BlocksCopied();
  stats.blocks_encoded = store::BlocksEncoded();
  stats.bytes_written += bytes;
  stats.overview_owed_tiles = overview_owed.size() + CycleOwedCount();
  stats.overviews_pending = cycle_levels >= 0 || !overview_owed.empty();
  EvictLocked();
  changed.notify_all();
}

void TileStore::Impl::PublishOnce(int64_t generation, std::unique_lock<std::mutex>& lock) {
  cycle_paused = false;  // A slice that failed tries again after this publish.
  PublishReport report;
  report.generation = generation;
  report.started = Clock::now();
  const double run_queue_start_ms = options.on_publish ? ThreadRunQueueMs() : 0.0;
  report.first_request = report.last_request = report.started;
  if (!request_time_of.empty()) {
    report.first_request = request_time_of.begin()->second;
    const auto last = request_time_of.upper_bound(generation);
    if (last != request_time_of.begin()) report.last_request = std::prev(last)->second;
  }
  report.refresh_slices = std::exchange(slices_refresh, 0);
  report.overview_slices = std::exchange(slices_overview, 0);
  report.slices_ms = std::exchange(slices_ms, 0.0);
  // 1. Snapshot what changed, under the lock (memory copies only).
  std::map<TileIndex, TileImage> level0;
  // Refreshed tiles wait for slices (they stay cached), unless closing, or more than
  // max_cached_tiles wait: then the publish takes the least recently painted of them, enough to
  // leave one slice fewer than the bound (the refresh slices' order). Until session 33 it took
  // them all: 66-132 tiles, 0.2-0.3 s of the writer in one publish at 25 fps with settled
  // re-renders, the publish latency's tail once early overview updates left it (docs/benchmarks.md,
  // "Session 33").
  std::set<TileIndex> refreshed_taken;
  if (!closing && refreshed_count > options.max_cached_tiles) {
    std::vector<std::pair<uint64_t, TileIndex>> order;
    for (const auto& [index, tile] : cache) {
      if (tile.refreshed && !tile.dirty) order.emplace_back(tile.last_use, index);
    }
    const size_t keep = options.max_cached_tiles -
                        std::min(options.max_cached_tiles,
                                 static_cast<size_t>(std::max(options.refresh_slice_tiles, 0)));
    const size_t n = order.size() - std::min(order.size(), keep);
    std::partial_sort(order.begin(), order.begin() + static_cast<std::ptrdiff_t>(n), order.end());
    for (size_t k = 0; k < n; ++k) refreshed_taken.insert(order[k].second);
  }
  refresh_paused = false;
  replaced_since_publish = false;
  ++publish_epoch;
  snapshot_changed.clear();
  for (auto& [index, tile] : cache) {
    if (!tile.dirty && !(tile.refreshed && (closing || refreshed_taken.count(index) > 0))) {
      continue;
    }
    // Copy-on-write: the snapshot shares the buffers (no copy under the lock); the next Paint
    // into this tile copies them first.
    level0[index] = tile.image;
    snapshot_changed[index] = std::exchange(tile.changed_blocks, 0);
    tile.shared = true;
    tile.writing = true;
    if (tile.dirty) --dirty_count;
    if (tile.refreshed) --refreshed_count;
    tile.dirty = false;
    tile.refreshed = false;
  }
  // Overviews and frames.gpkg at most every overview_interval_s after the last update ended,
  // and always when closing, or sooner when more than kOwedPerCachedTile x max_cached_tiles
  // tiles wait for them: the images they wait with stay in memory (a burst of re-renders,
  // e.g. the final solve's, touches hundreds), halved, so each takes a quarter of a cached
  // tile's memory. An update runs in slices between publishes, whether the clock or the bound
  // (counting the tiles owed since the last update started) starts it. Only when the tiles
  // waiting, these and what an update under way still owes, pass twice the bound (slices
  // falling behind a burst) does this publish bring the overviews up to date itself, which
  // delays the frames it publishes: when the bound alone did that, such publishes took 0.6-0.8 s
  // of the writer's wall time at 25 fps with settled re-renders, the publish latency's p99
  // (docs/benchmarks.md, "Session 33").
  size_t owed = overview_owed.size();
  for (const auto& [index, image] : level0) owed += overview_owed.count(index) ? 0 : 1;
  const bool live = !closing && options.overview_interval_s > 0.0;
  const size_t bound = kOwedPerCachedTile * options.max_cached_tiles;
  const bool idle = cycle_levels < 0;
  const bool by_clock =
      idle &&
      (!last_secondary || std::chrono::duration<double>(Clock::now() - *last_secondary).count() >=
                              options.overview_interval_s);
  const bool in_publish = live && owed + CycleOwedCount() > 2 * bound;
  const bool early = live && (in_publish || (!by_clock && idle && owed > bound));
  const bool secondary = !live || by_clock || early;
  const bool synchronous = !live || in_publish;
  stats.overview_updates += secondary ? 1 : 0;
  stats.overview_updates_early += early ? 1 : 0;
  stats.overview_updates_in_publish += in_publish ? 1 : 0;
  report.refreshed_tiles = static_cast<int>(refreshed_taken.size());
  report.overview_update = secondary;
  report.overview_update_early = early;
  report.overview_update_in_publish = synchronous;
  std::vector<FrameRecord> frames_to_write;
  if (secondary) frames_to_write.swap(frames_changed);
  // The records frames.gpkg does not hold yet go in the manifest (frames.pending), so that the
  // generation names every frame it shows even if the process dies before frames.gpkg follows.
  // A publish that writes frames.gpkg writes all of them there first.
  // A publish that finds frames.gpkg locked by another program puts the same list there.
  std::vector<FrameRecord> frames_pending;
  frames_pending.reserve(frames.size());
  for (const auto& [index, record] : frames) frames_pending.push_back(record);
  secondary_owed = !secondary;
  int64_t frame_count = frame_times.count();
  if (frames_time_stale) {  // Records loaded at open, or one replaced with another time.
    frames_time_stale = false;
    frames_time = {kNoTime, -kNoTime};
    frame_times.ForEach([this](double time_s) { WidenFramesTime(time_s); });
  }
  const double time_min = frame_count == 0 ? 0.0 : frames_time.first;
  const double time_max = frame_count == 0 ? 0.0 : frames_time.second;
  const std::string application = application_json;
  const auto planned = planned_bounds_px;
  application_dirty = false;
  lock.unlock();

  const Clock::time_point start = Clock::now();
  const double cpu_start_ms = ThreadCpuMs();
  const double system_start_ms = ThreadSystemCpuMs();
  int64_t bytes = 0, tiles_written = 0, overview_written = 0;
  std::string error;
  std::vector<TileIndex> snapshot;
  for (const auto& [index, image] : level0) snapshot.push_back(index);
  // The next manifest takes the published one's tile sets instead of a copy of them (a copy per
  // publish cost as much as the tiles flown, ~10^5 an hour) and notes the level-0 tiles it
  // adds; a failed publish takes those back. Overview tiles it lists stay listed: their files
  // are complete on disk.
  store::Manifest next;
  bool sets_taken = false;
  std::vector<TileIndex> added;
  try {
    // 2. Level-0 tiles, each to a temporary name then renamed.
    for (const auto& [index, image] : level0) {
      bytes += WriteLevel0Tile(index, image, snapshot_changed.at(index), lock);
      ++tiles_written;
    }
    // The published manifest changes only once the index is written.
    std::vector<store::LevelTiles> sets;
    sets.swap(manifest.levels);
    try {
      next = manifest;  // All but the sets.
    } catch (...) {
      manifest.levels.swap(sets);
      throw;
    }
    next.levels.swap(sets);
    sets_taken = true;
    const auto add = [&](const TileIndex& index) {
      if (next.levels[0].insert(index)) added.push_back(index);
    };
    for (const auto& [index, image] : level0) add(index);
    // Tiles a failed publish wrote are on disk but were never listed: listed now (they were
    // left out of the index until painted again), and their overviews read them from disk.
    for (const TileIndex& index : propagate_pending) {
      if (level0_on_disk.count(index)) {
        add(index);
        overview_owed.emplace(index, TileImage{});
      }
    }
    // Level 1 takes each changed tile halved: done now, so the writer lets go of the painters'
    // buffers at once (a tile painted again needs no copy) and the tile waits for its overview
    // update at a quarter of its size.
    for (const auto& [index, image] : level0) {
      overview_owed[index] = store::HalveTile(image, &Pools());
    }
    // The display range below reads the top level's tiles; with no overview level, these. The
    // references to the painters' buffers change hands under the lock (Paint reads the count).
    std::vector<TileImage> level0_top;
    lock.lock();
    if (secondary && LevelsFor(next.levels[0]) == 0) {
      for (const auto& [index, image] : level0) level0_top.push_back(image);
    }
    level0.clear();
    lock.unlock();
    // 3. Overviews: changed tiles propagate up, level by level; a level that did not exist is
    // built whole. Here when synchronous; otherwise in slices after this publish.
    std::vector<TileImage> top;
    if (secondary) StartOverviewCycle(&next);
    if (synchronous) {
      while (!OverviewStep(&next, std::numeric_limits<size_t>::max(), &bytes, &overview_written,
                           &top)) {
      }
      cycle_level0.clear();  // Done before this index: it lists them no more.
    }
    std::vector<const TileImage*> top_images;
    for (const TileImage& image : top) top_images.push_back(&image);
    for (const TileImage& image : level0_top) top_images.push_back(&image);
    const bool range_changed = WidenDisplayRange(&next, top_images) || qlr_owed;
    // 4. Frames, then the index: overview VRTs, mosaic.vrt, manifest.json.
    // Locked by another program past a short wait (a live publish must not stall on it; the
    // closing one waits longer): the records go in the manifest and wait for the next update.
    bool frames_written = false;
    if (secondary && (!frames_to_write.empty() || !fs::exists(root / "frames.gpkg"))) {
      frames_written = store::WriteFramesGpkg(
          root / "frames.gpkg", georef.crs_wkt, frames_to_write, options.durable,
          closing ? store::FramesGpkgClosingLockBudgetMs() : store::FramesGpkgLiveLockBudgetMs());
      report.frames_gpkg = frames_written;
      report.frames_gpkg_locked = !frames_written;
    }
    if (secondary && !report.frames_gpkg_locked) frames_pending.clear();
    next.frame_count = frame_count;
    next.time_min_s = time_min;
    next.time_max_s = time_max;
    next.application_json = application;
    next.planned_bounds_px = planned;
    next.frames_pending = std::move(frames_pending);
    const double index_ms_before = index_ms;
    WriteIndex(&next, generation);
    report.index_ms = index_ms - index_ms_before;
    index_owed = false;
    if (range_changed) WriteQlr(next);
    qlr_owed = false;
    manifest = std::move(next);
    sets_taken = false;
    propagate_pending.clear();
    if (synchronous && cycle_levels >= 0) FinishOverviewCycle(manifest);
  } catch (const Error& e) {
    error = e.what();
  } catch (const std::exception& e) {
    error = std::string("unexpected failure while publishing: ") + e.what();
  }
  if (!error.empty()) {
    propagate_pending.insert(snapshot.begin(), snapshot.end());
    cycle_paused = true;  // What the update owes stays owed; it goes on after the next publish.
  }
  if (sets_taken) {  // Failed: the level-0 set goes back as it was.
    for (const TileIndex& index : added) next.levels[0].erase(index);
    manifest.levels.swap(next.levels);
  }
  const double busy_ms = MsSince(start);
  const double cpu_ms = ThreadCpuMs() - cpu_start_ms;
  const double system_cpu_ms = ThreadSystemCpuMs() - system_start_ms;
  // The report goes out before the generation counts as published, so that a caller woken by
  // WaitPublished has its report; the files are on disk already. `finished` is the time
  // PublishedAt gives (latencies are counted to it, not to the end of the callback).
  report.finished = Clock::now();
  report.cpu_ms = cpu_ms;
  report.run_queue_ms = options.on_publish ? ThreadRunQueueMs() - run_queue_start_ms : 0.0;
  report.level0_tiles = static_cast<int>(tiles_written);
  report.overview_tiles = static_cast<int>(overview_written);
  report.failed = !error.empty();
  if (options.on_publish) {
    try {
      options.on_publish(report);
    } catch (...) {
      // Diagnostics only: a throwing callback must not stop the writer (the publish is done).
    }
  }

  lock.lock();
  stats.writer_busy_ms += busy_ms;
  stats.writer_cpu_ms += cpu_ms;
  stats.writer_system_cpu_ms += system_cpu_ms;
  stats.overview_owed_tiles = overview_owed.size() + CycleOwedCount();
  stats.overviews_pending = cycle_levels >= 0 || !overview_owed.empty();
  stats.index_ms_total = index_ms;
  stats.overview_reads = overview_reads;
  stats.index_bytes_total = index_bytes;
  stats.tiles_written += tiles_written + overview_written;
  stats.blocks_copied = store::BlocksCopied();
  stats.blocks_encoded = store::BlocksEncoded();
  stats.overview_tiles_written += overview_written;
  stats.bytes_written += bytes;
  if (error.empty()) {
    published_generation = generation;
    published_at.emplace_back(generation, report.finished);
    if (published_at.size() > 4096) {
      published_at_dropped_through = published_at.front().first;
      published_at.pop_front();
    }
    ++stats.publishes;
    if (report.frames_gpkg_locked) {
      // Still owed to frames.gpkg (the manifest holds them meanwhile).
      for (auto& record : frames_to_write) frames_changed.push_back(record);
      secondary_owed = true;
      ++stats.frames_gpkg_locked;
      if (closing) frames_gpkg_locked_at_close = true;
    } else {
      // Records now in frames.gpkg leave memory, unless put again since.
      for (const FrameRecord& record : frames_to_write) {
        const auto held = frames.find(record.index);
        if (held != frames.end() && SameRecord(held->second, record)) frames.erase(held);
      }
    }
    auto it = request_time_of.find(generation);
    if (it != request_time_of.end()) {
      publish_latencies_ms.push_back(MsSince(it->second));
      request_time_of.erase(request_time_of.begin(), std::next(it));
    }
  } else {
    failed_generation = generation;
    last_error = error;
    // What was not written stays dirty for the next attempt.
    for (auto& [index, tile] : cache) {
      if (tile.writing) {
        tile.writing = false;
        tile.changed_blocks = store::kAllBlocks;  // Its file may be either: encode it all.
        if (!tile.dirty) {
          tile.dirty = true;
          ++dirty_count;
          if (tile.refreshed) {
            tile.refreshed = false;
            --refreshed_count;
          }
        }
      }
    }
    for (auto& record : frames_to_write) frames_changed.push_back(record);
    application_dirty = true;
  }
  EvictLocked();
  changed.notify_all();
}

void TileStore::Impl::SyncLoop() {
  pthread_setname_np(pthread_self(), "irm-store-sync");
  const int fd = open(root.c_str(), O_RDONLY | O_DIRECTORY | O_CLOEXEC);
  if (fd < 0)
    return;  // Flushing is a service, not a condition of publishing: the kernel's own
             // write-back still runs.
  // At most a year: a longer wait would overflow the clock's nanoseconds and return at once.
  const auto interval = std::chrono::duration<double>(std::min(options.sync_interval_s, 3.2e7));
  std::unique_lock<std::mutex> lock(sync_mutex);
  while (!sync_wake.wait_for(lock, interval, [this] { return sync_stop; })) {
    lock.unlock();
    // A failure (EIO) surfaces where it matters, in the writes and renames of the publishes.
    if (syncfs(fd) == 0) ++syncs;
    lock.lock();
  }
  close(fd);
}

void TileStore::Impl::WriterLoop() {
  pthread_setname_np(pthread_self(), "irm-tile-writer");
  // Background work yields to the painting (registration) threads on a busy machine.
  LowerThisThreadPriority(options.writer_nice);
  std::unique_lock<std::mutex> lock(mutex);
  for (;;) {
    changed.wait(lock, [&] {
      return stop || requested_generation > started_generation || CycleRunnable() ||
             RefreshRunnable();
    });
    // Refreshed tiles and an overview update under way take one slice each after each
    // publish, and all the time the writer has between publishes: a publish waits for two
    // slices at most, and the work ends within as many publishes as it has slices even when
    // the writer is never idle.
    const bool refresh_now = RefreshRunnable() && refresh_turn;
    const bool overview_now = CycleRunnable() && slice_turn;
    if (requested_generation > started_generation && !refresh_now && !overview_now) {
      started_generation = requested_generation;
      PublishOnce(started_generation, lock);
      slice_turn = true;
      refresh_turn = true;
      continue;
    }
    if (stop && requested_generation <= started_generation) return;
    if (RefreshRunnable() && (refresh_now || !overview_now)) {
      RefreshSlice(lock);
      refresh_turn = false;
    } else if (CycleRunnable()) {
      OverviewSlice(lock);
      slice_turn = false;
    }
  }
}

TileStore::TileStore(std::unique_ptr<Impl> impl) : impl_(std::move(impl)) {}

TileStore::~TileStore() {
  try {
    Close();
  } catch (const std::exception&) {
    // Close() reports; a destructor must not throw. What was published stays valid.
  }
}

std::unique_ptr<TileStore> TileStore::Open(const TileStoreOptions& requested,
                                           const StoreGeoreference& georef) {
  TileStoreOptions options = requested;
  std::string problem;
  if (!options.IsValid(&problem)) {
    throw InputError({options.path, 0, 0, "options"}, problem, "fix the option named");
  }
  if (!(georef.gsd_m > 0.0) || !std::isfinite(georef.gsd_m) || georef.crs_wkt.empty()) {
    throw InputError({options.path, 0, 0, "georeference"},
                     "the georeference needs a positive gsd_m and the mosaic CRS WKT",
                     "pass LocalFrame::CrsWkt() and the mosaic GSD");
  }
  GDALAllRegister();
  auto impl = std::make_unique<Impl>();
  impl->options = options;
  impl->georef = georef;
  impl->type = options.pixel_type;
  impl->root = fs::path(options.path);
  impl->max_levels = MaxLevelsFor(options.tile_size);
  const fs::path manifest_path = impl->root / "manifest.json";
  std::error_code error;
  bool exists = fs::exists(impl->root, error);
  const bool is_store = fs::exists(manifest_path, error);
  bool empty_dir = exists && fs::is_directory(impl->root, error) &&
                   fs::directory_iterator(impl->root, error) == fs::directory_iterator();

  using Mode = TileStoreOptions::Mode;
  // A run killed before its first publish leaves no manifest: nothing was published, so
  // --resume and --overwrite start afresh (found by the kill -9 campaign, scripts/faults.sh).
  // Only the skeleton of an interrupted creation qualifies: no tile, nothing foreign.
  if (options.mode != Mode::kCreate && exists && !is_store && !empty_dir &&
      fs::is_directory(impl->root, error)) {
    bool skeleton = true;
    for (const auto& entry : fs::recursive_directory_iterator(impl->root, error)) {
      const std::string name = entry.path().filename().string();
      if (entry.is_directory() || store::IsTemporaryName(name) ||
          name.rfind("frames.gpkg", 0) == 0 || entry.path().extension() == ".qlr") {
        continue;
      }
      skeleton = false;
      break;
    }
    if (skeleton && !error) {
      fs::remove_all(impl->root, error);
      exists = fs::exists(impl->root, error);
    }
  }
  if (options.mode == Mode::kResume && (!exists || empty_dir)) {
    options.mode = Mode::kCreate;  // Nothing was ever published: resuming is creating.
    impl->options.mode = Mode::kCreate;
  }
  if (options.mode == Mode::kCreate && exists && !empty_dir) {
    throw InputError(
        {options.path, 0, 0, ""},
        is_store ? "a store already exists here" : "the path exists and is not an empty folder",
        is_store ? "pass --resume to continue it or --overwrite to replace it"
                 : "choose a new path");
  }
  if (options.mode == Mode::kOverwrite && exists && !empty_dir) {
    if (!is_store) {
      throw InputError({options.path, 0, 0, ""},
                       "the path exists and is not an irmosaic store; refusing "
                       "to delete it",
                       "choose a new path, or remove it yourself");
    }
    fs::remove_all(impl->root, error);
    if (error) {
      throw OutputError("cannot remove the old store " + options.path + ": " + error.message() +
                        ". Fix: check the folder's permissions");
    }
  }
  Impl& s = *impl;
  if (options.mode == Mode::kResume) {
    if (!is_store) {
      throw InputError({options.path, 0, 0, ""}, "there is no store to resume here",
                       "run without --resume to create it");
    }
    s.manifest = store::ReadManifest(manifest_path);
    const StoreGeoreference& old = s.manifest.georef;
    if (std::abs(old.origin_lat_deg - georef.origin_lat_deg) > 1e-9 ||
        std::abs(old.origin_lon_deg - georef.origin_lon_deg) > 1e-9 ||
        std::abs(old.gsd_m - georef.gsd_m) > 1e-12 || s.manifest.tile_size != options.tile_size) {
      throw InputError({manifest_path.string(), 0, 0, ""},
                       "the store's origin, GSD or tile size differ from this run's",
                       "resume with the settings of the interrupted run, or use --overwrite");
    }
    s.type = s.manifest.type;
    s.created_utc = s.manifest.created_utc;
    s.level0_on_disk = s.manifest.levels.empty() ? store::LevelTiles{} : s.manifest.levels[0];
    s.application_json = s.manifest.application_json;
    s.planned_bounds_px = s.manifest.planned_bounds_px;
    s.published_generation = s.requested_generation = s.started_generation = s.manifest.generation;
    for (const FrameRecord& record : store::ReadFramesGpkg(s.root / "frames.gpkg")) {
      s.frame_times.Set(record.index, record.time_s);
    }
    // Overviews behind level 0 when the process ended (killed between overview updates): the
    // tiles the index lists as owed, and listed tiles written after it (by re-render slices, or
    // by a publish killed before its index), are brought into the overviews from their files.
    std::error_code time_error;
    const fs::file_time_type index_time = fs::last_write_time(manifest_path, time_error);
    for (const TileIndex& index : s.manifest.overviews_owed) {
      if (s.level0_on_disk.count(index)) s.overview_owed.emplace(index, TileImage{});
    }
    if (!time_error) {
      for (const TileIndex& index : s.level0_on_disk.tiles()) {
        std::error_code stat_error;
        const fs::file_time_type t = fs::last_write_time(s.PathOf(0, index), stat_error);
        if (!stat_error && t >= index_time) s.overview_owed.emplace(index, TileImage{});
      }
    }
    s.secondary_owed = !s.overview_owed.empty();  // Even if nothing is painted again.
    // Records the published generation holds that frames.gpkg missed (the process died before
    // frames.gpkg followed): put again, written with the next frames.gpkg update.
    for (const FrameRecord& record : s.manifest.frames_pending) {
      s.frame_times.Set(record.index, record.time_s);  // Times widened at the first publish.
      s.frames[record.index] = record;
      s.frames_changed.push_back(record);
    }
    // Temporaries of an interrupted publish are garbage: the manifest never named them.
    for (const auto& entry : fs::recursive_directory_iterator(s.root, error)) {
      if (store::IsTemporaryName(entry.path().filename().string())) {
        std::error_code ignored;
        fs::remove(entry.path(), ignored);
      }
    }
  } else {
    fs::create_directories(s.root / "tiles" / "0", error);
    if (error) {
      throw OutputError("cannot create the store folder " + options.path + ": " + error.message() +
                        ". Fix: choose a writable folder");
    }
    s.created_utc = store::UtcNow();
    s.manifest.georef = georef;
    s.manifest.tile_size = options.tile_size;
    s.manifest.type = s.type;
    s.manifest.compression = options.compression;
    s.manifest.created_utc = s.created_utc;
    s.manifest.levels.resize(1);
    // Generation 0: an empty but valid store, so readers and the .qlr work from the start.
    store::CreateFramesGpkg(s.root / "frames.gpkg", georef.crs_wkt, options.durable);
    s.WriteIndex(&s.manifest, 0);
  }
  s.manifest.compression = options.compression;
  if (!fs::exists(s.root / (options.layer_name + ".qlr")) ||
      !fs::exists(s.root / (options.layer_name + "_live.qlr"))) {
    s.WriteQlr(s.manifest);
  }
  s.layouts = std::make_unique<LayoutCache>(8 * options.max_cached_tiles + 64);
  s.writer = std::thread([&s] { s.WriterLoop(); });
  if (options.sync_interval_s > 0.0) s.syncer = std::thread([&s] { s.SyncLoop(); });
  return std::unique_ptr<TileStore>(new TileStore(std::move(impl)));
}

std::unique_ptr<TileStore> TileStore::OpenReadOnly(const std::string& path) {
  GDALAllRegister();
  auto impl = std::make_unique<Impl>();
  impl->root = fs::path(path);
  impl->manifest = store::ReadManifest(impl->root / "manifest.json");
  impl->read_only = true;
  impl->georef = impl->manifest.georef;
  impl->type = impl->manifest.type;
  impl->options.path = path;
  impl->options.tile_size = impl->manifest.tile_size;
  impl->options.pixel_type = impl->type;
  impl->options.compression = impl->manifest.compression;
  impl->level0_on_disk =
      impl->manifest.levels.empty() ? store::LevelTiles{} : impl->manifest.levels[0];
  impl->published_generation = impl->manifest.generation;
  impl->application_json = impl->manifest.application_json;
  // Read from frames.gpkg by FrameRecords(): checked here, so a damaged store fails to open.
  for (const FrameRecord& record : store::ReadFramesGpkg(impl->root / "frames.gpkg")) {
    impl->frame_times.Set(record.index, record.time_s);
  }
  // The published generation's records that frames.gpkg does not hold yet.
  for (const FrameRecord& record : impl->manifest.frames_pending) {
    impl->frame_times.Set(record.index, record.time_s);
    impl->frames[record.index] = record;
  }
  return std::unique_ptr<TileStore>(new TileStore(std::move(impl)));
}

void TileStore::Paint(const cv::Mat& image, const cv::Mat& weight, cv::Point origin_px,
                      PaintKind kind) {
  Impl& s = *impl_;
  if (s.read_only) {
    throw Error("TileStore::Paint on a store opened read-only (" + s.options.path + ")");
  }
  if (image.empty()) return;
  if (image.channels() != 1 || image.depth() != CvDepthOf(s.type) || weight.type() != CV_32F ||
      weight.size() != image.size()) {
    throw InputError({s.options.path, 0, 0, "Paint"},
                     "patch must be one channel of the store's type (" +
                         std::string(GdalTypeNameOf(s.type)) +
                         ") with a CV_32F weight of the same size",
                     "convert the patch to the store's pixel type");
  }
  const Clock::time_point start = Clock::now();
  const int t = s.options.tile_size;
  const int64_t row0 = TileIndexOf(origin_px.y, t),
                row1 = TileIndexOf(origin_px.y + image.rows - 1, t);
  const int64_t col0 = TileIndexOf(origin_px.x, t),
                col1 = TileIndexOf(origin_px.x + image.cols - 1, t);
  std::unique_lock<std::mutex> lock(s.mutex);
  if (s.stop) throw Error("TileStore::Paint after Close (" + s.options.path + ")");
  for (int64_t row = row0; row <= row1; ++row) {
    for (int64_t col = col0; col <= col1; ++col) {
      // The part of the patch inside this tile, in patch and tile pixels.
      const int64_t tx = col * t, ty = row * t;
      const int64_t x0 = std::max<int64_t>(tx, origin_px.x),
                    y0 = std::max<int64_t>(ty, origin_px.y);
      const int64_t x1 = std::min<int64_t>(tx + t, origin_px.x + image.cols);
      const int64_t y1 = std::min<int64_t>(ty + t, origin_px.y + image.rows);
      const cv::Rect patch_roi(static_cast<int>(x0 - origin_px.x),
                               static_cast<int>(y0 - origin_px.y), static_cast<int>(x1 - x0),
                               static_cast<int>(y1 - y0));
      const cv::Rect tile_roi(static_cast<int>(x0 - tx), static_cast<int>(y0 - ty), patch_roi.width,
                              patch_roi.height);
      if (!AnyPositiveWeight(weight, patch_roi)) continue;
      Impl::CachedTile& tile = s.TileLocked({row, col}, lock);
      if (tile.shared) {
        // Every reference the writer takes or drops is taken or dropped under this lock, so the
        // count is current: one (the cache's own, plus the pool's) once the writer let go.
        store::TilePools& pools = s.Pools();
        if (SharedBuffer(tile.image.data, pools.data) ||
            SharedBuffer(tile.image.alpha, pools.alpha)) {
          store::TileImage copy = pools.Blank();
          tile.image.data.copyTo(copy.data);
          tile.image.alpha.copyTo(copy.alpha);
          tile.image = std::move(copy);
          ++s.stats.tile_copies;
        }
        tile.shared = false;
      }
      bool painted = false;
      switch (s.type) {
        case PixelType::kByte:
          painted = BlendInto<uint8_t>(image, weight, patch_roi, &tile.image.data,
                                       &tile.image.alpha, tile_roi);
          break;
        case PixelType::kUInt16:
          painted = BlendInto<uint16_t>(image, weight, patch_roi, &tile.image.data,
                                        &tile.image.alpha, tile_roi);
          break;
        case PixelType::kFloat32:
          painted = BlendInto<float>(image, weight, patch_roi, &tile.image.data, &tile.image.alpha,
                                     tile_roi);
          break;
      }
      if (!painted) continue;
      tile.changed_blocks |= BlocksPainted(weight, patch_roi, tile_roi, t);
      tile.paint_epoch = s.publish_epoch;
      // A refresh of a tile on disk may wait for a refresh slice; anything else goes out with
      // the next publish.
      if (kind == PaintKind::kRefresh && s.options.refresh_slice_tiles > 0 &&
          s.level0_on_disk.count({row, col})) {
        if (!tile.dirty && !tile.refreshed) {
          tile.refreshed = true;
          ++s.refreshed_count;  // Ready after the next publish, which wakes the writer.
        }
      } else if (!tile.dirty) {
        tile.dirty = true;
        ++s.dirty_count;
        if (tile.refreshed) {
          tile.refreshed = false;
          --s.refreshed_count;
        }
      }
    }
  }
  s.EvictLocked();
  // Back-pressure: memory stays bounded when painting outruns the writer.
  if (s.cache.size() > 2 * s.options.max_cached_tiles) {
    if (s.requested_generation <= s.started_generation) {
      s.request_time_of[++s.requested_generation] = Clock::now();
      s.changed.notify_all();
    }
    const Clock::time_point wait_start = Clock::now();
    s.changed.wait(lock, [&] {
      return s.cache.size() <= 2 * s.options.max_cached_tiles ||
             s.failed_generation >= s.requested_generation || s.stop;
    });
    ++s.stats.paint_waits;
    s.stats.paint_wait_ms_total += MsSince(wait_start);
  }
  s.stats.paint_ms_total += MsSince(start);
}

void TileStore::PutFrameRecord(const FrameRecord& record) {
  Impl& s = *impl_;
  if (record.index < 0) {
    throw InputError({s.options.path, 0, 0, "FrameRecord.index"},
                     "frame index " + std::to_string(record.index) + " is negative",
                     "number frames from 0");
  }
  std::lock_guard<std::mutex> lock(s.mutex);
  const std::optional<double> old_time = s.frame_times.Set(record.index, record.time_s);
  if (old_time && *old_time != record.time_s) s.frames_time_stale = true;
  s.frames[record.index] = record;
  if (!s.frames_time_stale) s.WidenFramesTime(record.time_s);
  s.frames_changed.push_back(record);
}

std::vector<FrameRecord> TileStore::FrameRecords() const {
  // The records in memory first, then frames.gpkg's: a record written and dropped meanwhile
  // is in the file by then, and one put meanwhile is newer than this call.
  std::map<int64_t, FrameRecord> held;
  {
    std::lock_guard<std::mutex> lock(impl_->mutex);
    held = impl_->frames;
  }
  std::map<int64_t, FrameRecord> all;
  for (FrameRecord& record : store::ReadFramesGpkg(impl_->root / "frames.gpkg")) {
    all[record.index] = std::move(record);
  }
  for (auto& [index, record] : held) all[index] = std::move(record);
  std::vector<FrameRecord> records;
  records.reserve(all.size());
  for (auto& [index, record] : all) records.push_back(std::move(record));
  return records;
}

void TileStore::SetApplicationState(const std::string& json_text) {
  if (!json_text.empty() && !nlohmann::json::accept(json_text)) {
    throw InputError({impl_->options.path, 0, 0, "application state"}, "not valid JSON",
                     "pass a JSON document");
  }
  std::lock_guard<std::mutex> lock(impl_->mutex);
  impl_->application_json = json_text;
  impl_->application_dirty = true;
}

void TileStore::SetPlannedBoundsPx(const cv::Rect& mosaic_px) {
  std::lock_guard<std::mutex> lock(impl_->mutex);
  if (mosaic_px.empty()) {
    impl_->application_dirty |= impl_->planned_bounds_px.has_value();
    impl_->planned_bounds_px.reset();
    return;
  }
  const std::array<int64_t, 4> planned = {mosaic_px.x, mosaic_px.y, mosaic_px.br().x,
                                          mosaic_px.br().y};
  if (impl_->planned_bounds_px == planned) return;
  impl_->planned_bounds_px = planned;
  impl_->application_dirty = true;  // The manifest changes even if no tile does.
}

std::string TileStore::application_state() const {
  std::lock_guard<std::mutex> lock(impl_->mutex);
  return impl_->application_json;
}

int64_t TileStore::RequestPublish() {
  Impl& s = *impl_;
  std::lock_guard<std::mutex> lock(s.mutex);
  if (s.read_only) return s.published_generation;
  // A request not yet started by the writer already covers everything painted so far.
  if (s.requested_generation > s.started_generation) return s.requested_generation;
  // Nothing new since the writer's last snapshot: that generation already holds it all.
  // Closing, an overview update still under way needs the last publish too (it finishes it).
  // Refreshed tiles wait for a publish too: those painted before it are written after it.
  const bool changed = s.dirty_count > 0 || s.refreshed_count > 0 || s.replaced_since_publish ||
                       !s.frames_changed.empty() || s.application_dirty || s.secondary_owed ||
                       s.failed_generation >= s.started_generation ||
                       (s.closing && (s.stats.overviews_pending || s.refreshed_count > 0));
  if (!changed) return s.started_generation;
  ++s.requested_generation;
  s.request_time_of[s.requested_generation] = Clock::now();
  s.changed.notify_all();
  return s.requested_generation;
}

void TileStore::WaitPublished(int64_t generation) {
  Impl& s = *impl_;
  std::unique_lock<std::mutex> lock(s.mutex);
  s.changed.wait(lock, [&] {
    return s.published_generation >= generation || s.failed_generation >= generation || s.closed;
  });
  if (s.published_generation < generation) {
    throw OutputError(s.last_error.empty() ? "store " + s.options.path + " is closed"
                                           : s.last_error);
  }
}

int64_t TileStore::published_generation() const {
  std::lock_guard<std::mutex> lock(impl_->mutex);
  return impl_->published_generation;
}

double TileStore::BacklogSeconds() const {
  const Impl& s = *impl_;
  std::lock_guard<std::mutex> lock(s.mutex);
  if (s.requested_generation <= s.published_generation ||
      s.failed_generation >= s.requested_generation) {
    return 0.0;
  }
  const auto it = s.request_time_of.upper_bound(s.published_generation);
  if (it == s.request_time_of.end()) return 0.0;
  return std::chrono::duration<double>(Clock::now() - it->second).count();
}

std::optional<std::chrono::steady_clock::time_point> TileStore::PublishedAt(
    int64_t generation) const {
  std::lock_guard<std::mutex> lock(impl_->mutex);
  const auto& times = impl_->published_at;
  const auto it = std::lower_bound(
      times.begin(), times.end(), generation,
      [](const std::pair<int64_t, Clock::time_point>& p, int64_t g) { return p.first < g; });
  if (it == times.end() || (impl_->published_at_dropped_through > 0 &&
                            generation <= impl_->published_at_dropped_through)) {
    return std::nullopt;
  }
  return it->second;
}

void TileStore::ReadWindow(const cv::Rect& mosaic_px, cv::Mat* image, cv::Mat* coverage) const {
  const Impl& s = *impl_;
  const int t = s.options.tile_size;
  *image = cv::Mat::zeros(mosaic_px.size(), CvDepthOf(s.type));
  *coverage = cv::Mat::zeros(mosaic_px.size(), CV_8U);
  if (mosaic_px.empty()) return;
  for (int64_t row = TileIndexOf(mosaic_px.y, t); row <= TileIndexOf(mosaic_px.br().y - 1, t);
       ++row) {
    for (int64_t col = TileIndexOf(mosaic_px.x, t); col <= TileIndexOf(mosaic_px.br().x - 1, t);
         ++col) {
      TileImage tile;
      {
        std::lock_guard<std::mutex> lock(s.mutex);
        auto it = s.cache.find({row, col});
        if (it != s.cache.end()) {
          tile = {it->second.image.data.clone(), it->second.image.alpha.clone()};
        } else if (!s.level0_on_disk.count({row, col})) {
          continue;
        }
      }
      if (tile.empty()) tile = store::ReadTile(s.PathOf(0, {row, col}), t, s.type);
      const cv::Rect tile_rect(static_cast<int>(col * t), static_cast<int>(row * t), t, t);
      const cv::Rect overlap = tile_rect & mosaic_px;
      const cv::Rect in_tile = overlap - tile_rect.tl();
      const cv::Rect in_window = overlap - mosaic_px.tl();
      tile.data(in_tile).copyTo((*image)(in_window));
      tile.alpha(in_tile).copyTo((*coverage)(in_window));
    }
  }
}

void TileStore::Close() {
  Impl& s = *impl_;
  if (s.read_only || !s.writer.joinable()) return;
  std::string error;
  {
    std::lock_guard<std::mutex> lock(s.mutex);
    s.closing = true;  // The last publish defers nothing.
  }
  try {
    WaitPublished(RequestPublish());
  } catch (const Error& e) {
    error = e.what();
  }
  {
    std::lock_guard<std::mutex> lock(s.mutex);
    s.stop = true;
    s.changed.notify_all();
  }
  s.writer.join();
  if (s.syncer.joinable()) {
    {
      std::lock_guard<std::mutex> lock(s.sync_mutex);
      s.sync_stop = true;
    }
    s.sync_wake.notify_all();
    s.syncer.join();
  }
  if (error.empty() && s.frames_gpkg_locked_at_close) {
    error = "cannot write " + (s.root / "frames.gpkg").string() + ": another program held it " +
            "locked for " + std::to_string(store::FramesGpkgClosingLockBudgetMs()) +
            " ms (\"database is locked\"); the last frames' records are in manifest.json " +
            "(frames.pending), which a resume takes. Fix: close the program that has " +
            "frames.gpkg open for writing, then resume the store (irmosaic run --resume, or " +
            "TileStoreOptions::Mode::kResume) to move them into frames.gpkg";
  }
  if (error.empty()) store::SettleFramesGpkg(s.root / "frames.gpkg");
  {
    std::lock_guard<std::mutex> lock(s.mutex);
    s.closed = true;
    s.changed.notify_all();
  }
  if (!error.empty()) throw OutputError(error);
}

TileStore::Stats TileStore::stats() const {
  const Impl& s = *impl_;
  std::lock_guard<std::mutex> lock(s.mutex);
  Stats out = s.stats;
  out.syncs = s.syncs.load();
  out.frame_records_held = s.frames.size();
  std::vector<double> latencies = s.publish_latencies_ms;
  if (!latencies.empty()) {
    std::sort(latencies.begin(), latencies.end());
    const auto at = [&](double q) {
      return latencies[std::min(latencies.size() - 1,
                                static_cast<size_t>(std::ceil(q * latencies.size())) - 1)];
    };
    out.publish_p50_ms = at(0.5);
    out.publish_p99_ms = at(0.99);
    out.publish_max_ms = latencies.back();
  }
  out.cached_tiles = s.cache.size();
  out.refresh_waiting = s.refreshed_count;
  out.tiles_on_disk = s.level0_on_disk.size();
  return out;
}

cv::Rect TileStore::level0_bounds_px() const {
  const Impl& s = *impl_;
  std::lock_guard<std::mutex> lock(s.mutex);
  store::LevelTiles all = s.level0_on_disk;  // A copy of its blocks, not of every tile.
  for (const auto& [index, tile] : s.cache) {
    if (tile.dirty || tile.writing) all.insert(index);  // Not the blank tiles of zero weights.
  }
  if (all.empty()) return {};
  const store::TileBounds b = all.bounds();
  const int t = s.options.tile_size;
  return {static_cast<int>(b.col0 * t), static_cast<int>(b.row0 * t),
          static_cast<int>((b.col1 - b.col0) * t), static_cast<int>((b.row1 - b.row0) * t)};
}

const TileStoreOptions& TileStore::options() const { return impl_->options; }
const StoreGeoreference& TileStore::georeference() const { return impl_->georef; }
PixelType TileStore::pixel_type() const { return impl_->type; }

}  // namespace irmosaic
