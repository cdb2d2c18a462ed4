// The files of a TileStore: tile GeoTIFFs, atomic writes, the manifest, the VRTs and frames.gpkg.
#include <cpl_conv.h>
#include <cpl_error.h>
#include <cpl_vsi.h>
#include <fcntl.h>
#include <gdal.h>
#include <gdal_priv.h>
#include <ogrsf_frmts.h>
#include <sys/stat.h>
#include <tiffio.h>
#include <unistd.h>
#include <zstd.h>

#include <algorithm>
#include <array>
#include <atomic>
#include <bit>
#include <charconv>
#include <chrono>
#include <cmath>
#include <cstring>
#include <ctime>
#include <fstream>
#include <map>
#include <mutex>
#include <nlohmann/json.hpp>
#include <opencv2/core/hal/intrin.hpp>
#include <opencv2/imgproc.hpp>
#include <optional>
#include <set>
#include <sstream>
#include <thread>
#include <tuple>

#if defined(__SSE2__)
#include <emmintrin.h>
#endif

#include "irmosaic/error.h"
#include "store_internal.h"

namespace irmosaic::store {

namespace fs = std::filesystem;

namespace {

// Collects GDAL errors of this thread while alive, so a failed write becomes one OutputError.
class GdalErrorCapture {
 public:
  GdalErrorCapture() { CPLPushErrorHandlerEx(&Handler, this); }
  ~GdalErrorCapture() { CPLPopErrorHandler(); }
  bool failed() const { return !message_.empty(); }
  const std::string& message() const { return message_; }

 private:
  static void CPL_STDCALL Handler(CPLErr level, CPLErrorNum, const char* text) {
    auto* self = static_cast<GdalErrorCapture*>(CPLGetErrorHandlerUserData());
    if (level >= CE_Failure && self->message_.empty()) self->message_ = text ? text : "error";
  }
  std::string message_;
};

std::atomic<int64_t> g_temp_counter{0};

fs::path TemporaryPathFor(const fs::path& path) {
  return path.parent_path() /
         ("." + path.filename().string() + ".tmp" + std::to_string(::getpid()) + "_" +
          std::to_string(g_temp_counter.fetch_add(1)));
}

void FsyncFile(const fs::path& path) {
  const int fd = ::open(path.c_str(), O_RDONLY);
  if (fd >= 0) {
    ::fsync(fd);
    ::close(fd);
  }
}

void RenameOrThrow(const fs::path& from, const fs::path& to, bool durable) {
  if (durable) FsyncFile(from);
  std::error_code error;
  fs::rename(from, to, error);
  if (error) {
    fs::remove(from, error);
    throw OutputError("cannot rename " + from.string() + " to " + to.string() + ": " +
                      error.message() + ". Fix: check the store folder's permissions");
  }
  if (durable) FsyncFile(to.parent_path());
}

GDALDataType GdalTypeOf(PixelType type) {
  switch (type) {
    case PixelType::kByte:
      return GDT_Byte;
    case PixelType::kUInt16:
      return GDT_UInt16;
    case PixelType::kFloat32:
      return GDT_Float32;
  }
  return GDT_Unknown;
}

std::string XmlEscape(const std::string& text) {
  std::string out;
  out.reserve(text.size());
  for (char c : text) {
    switch (c) {
      case '&':
        out += "&amp;";
        break;
      case '<':
        out += "&lt;";
        break;
      case '>':
        out += "&gt;";
        break;
      case '"':
        out += "&quot;";
        break;
      default:
        out += c;
    }
  }
  return out;
}

std::string FormatGeoTransform(const double gt[6]) {
  std::ostringstream text;
  text.precision(17);
  text << gt[0] << ", " << gt[1] << ", " << gt[2] << ", " << gt[3] << ", " << gt[4] << ", "
       << gt[5];
  return text.str();
}

}  // namespace

double AlphaMaxOf(PixelType type) { return type == PixelType::kUInt16 ? 65535.0 : 255.0; }

PixelType PixelTypeFromName(const std::string& name) {
  if (name == "Byte") return PixelType::kByte;
  if (name == "UInt16") return PixelType::kUInt16;
  if (name == "Float32") return PixelType::kFloat32;
  throw Error("unknown pixel type '" + name + "' (expected Byte, UInt16 or Float32)");
}

TileImage EmptyTile(int tile_size, PixelType type) {
  return {cv::Mat::zeros(tile_size, tile_size, CvDepthOf(type)),
          cv::Mat::zeros(tile_size, tile_size, CV_8U)};
}

TilePools::TilePools(int tile_size, PixelType type, size_t capacity)
    : data(tile_size, tile_size, CvDepthOf(type), capacity),
      alpha(tile_size, tile_size, CV_8U, capacity),
      half_data(tile_size / 2, tile_size / 2, CvDepthOf(type), capacity),
      half_alpha(tile_size / 2, tile_size / 2, CV_8U, capacity) {}

TileImage TilePools::Blank() { return {data.Take(), alpha.Take()}; }
TileImage TilePools::Empty() { return {data.TakeZeros(), alpha.TakeZeros()}; }
TileImage TilePools::HalfBlank() { return {half_data.Take(), half_alpha.Take()}; }

TileImage EmptyTile(TilePools* pools) { return pools->Empty(); }

std::string TileRelativePath(int level, const TileIndex& tile) {
  return "tiles/" + std::to_string(level) + "/" + std::to_string(tile.first) + "_" +
         std::to_string(tile.second) + ".tif";
}

void TileGeoTransform(double gsd_m, int tile_size, int level, const TileIndex& tile, double gt[6]) {
  const double scale = std::ldexp(1.0, level);
  // Level-0 pixel (col, row) is centred on plane (col*gsd, -row*gsd): its top-left corner is
  // half a pixel up and left. A level-l tile starts at level-0 pixel tile*T*2^l.
  const double col0 = static_cast<double>(tile.second) * tile_size * scale;
  const double row0 = static_cast<double>(tile.first) * tile_size * scale;
  gt[0] = (col0 - 0.5) * gsd_m;
  gt[1] = gsd_m * scale;
  gt[2] = 0.0;
  gt[3] = -(row0 - 0.5) * gsd_m;
  gt[4] = 0.0;
  gt[5] = -gsd_m * scale;
}

bool IsTemporaryName(const std::string& filename) {
  return !filename.empty() && filename[0] == '.' && filename.find(".tmp") != std::string::npos;
}

void WriteFileAtomic(const fs::path& path, const std::string& content, bool durable) {
  const fs::path temp = TemporaryPathFor(path);
  {
    std::ofstream out(temp, std::ios::binary | std::ios::trunc);
    out.write(content.data(), static_cast<std::streamsize>(content.size()));
    out.flush();
    if (!out) {
      std::error_code ignored;
      fs::remove(temp, ignored);
      throw OutputError("cannot write " + path.string() + " (" + std::strerror(errno) +
                        "). Fix: free disk space or check the folder's permissions; the "
                        "published store is unchanged");
    }
  }
  RenameOrThrow(temp, path, durable);
}

namespace {

thread_local int64_t t_direct_tile_writes = 0;
thread_local int64_t t_blocks_copied = 0, t_blocks_encoded = 0;

// GDAL's GTiff encoding of a tile, in memory; `data` is CPLFree'd with the holder.
struct GdalEncoded {
  GByte* data = nullptr;
  vsi_l_offset length = 0;
  std::string failure;
  GdalEncoded() = default;
  GdalEncoded(const GdalEncoded&) = delete;
  GdalEncoded& operator=(const GdalEncoded&) = delete;
  ~GdalEncoded() { CPLFree(data); }
};

void EncodeWithGdal(const TileImage& tile, const double gt[6], const TileWriteSettings& settings,
                    GdalEncoded* out) {
  // GDAL encodes the file in memory (/vsimem), then it goes to disk in one write instead of
  // libtiff's many small writes and seeks: 3.7 -> 3.35 CPU ms per 512 x 512 UInt16 tile of a
  // flight, with the creation options no longer validated per tile (docs/benchmarks.md,
  // "Session 9").
  const std::string memory_path = "/vsimem/irmosaic_tile_" + std::to_string(::getpid()) + "_" +
                                  std::to_string(g_temp_counter.fetch_add(1)) + ".tif";
  const int size = tile.data.cols;
  const int block = std::min(kBlockSize, size);
  CPLStringList options;
  options.SetNameValue("TILED", "YES");
  options.SetNameValue("BLOCKXSIZE", std::to_string(block).c_str());
  options.SetNameValue("BLOCKYSIZE", std::to_string(block).c_str());
  options.SetNameValue("INTERLEAVE", "BAND");
  options.SetNameValue("PHOTOMETRIC", "MINISBLACK");
  options.SetNameValue("ALPHA", "YES");
  options.SetNameValue("COMPRESS", settings.compression.c_str());
  if (settings.compression != "NONE") {
    options.SetNameValue("PREDICTOR", settings.type == PixelType::kFloat32 ? "3" : "2");
    const std::string level = std::to_string(settings.compression_level);
    if (settings.compression == "ZSTD") options.SetNameValue("ZSTD_LEVEL", level.c_str());
    if (settings.compression == "DEFLATE") options.SetNameValue("ZLEVEL", level.c_str());
  }
  cv::Mat alpha;
  tile.alpha.convertTo(alpha, CvDepthOf(settings.type), AlphaMaxOf(settings.type) / 255.0);
  GdalErrorCapture capture;
  GDALDriver* driver = GetGDALDriverManager()->GetDriverByName("GTiff");
  GDALDatasetH dataset = nullptr;
  if (driver != nullptr && driver->pfnCreate != nullptr) {
    // The driver's own creation, without what GDALDriver::Create does first: delete an existing
    // dataset of that name (it asks every registered driver whether it knows the name, ~6 % of
    // the writer's CPU; this /vsimem name is new) and validate the options (fixed and valid).
    dataset = GDALDataset::ToHandle(driver->pfnCreate(memory_path.c_str(), size, size, 2,
                                                      GdalTypeOf(settings.type), options.List()));
  } else if (driver != nullptr) {
    const CPLConfigOptionSetter no_validation("GDAL_VALIDATE_CREATION_OPTIONS", "NO", false);
    dataset = GDALCreate(GDALDriver::ToHandle(driver), memory_path.c_str(), size, size, 2,
                         GdalTypeOf(settings.type), options.List());
  }
  if (dataset != nullptr) {
    GDALSetGeoTransform(dataset, const_cast<double*>(gt));
    GDALSetProjection(dataset, settings.crs_wkt.c_str());
    const GDALDataType type = GdalTypeOf(settings.type);
    CPLErr status = GDALRasterIO(GDALGetRasterBand(dataset, 1), GF_Write, 0, 0, size, size,
                                 const_cast<uchar*>(tile.data.ptr()), size, size, type, 0,
                                 static_cast<int>(tile.data.step[0]));
    if (status == CE_None) {
      status = GDALRasterIO(GDALGetRasterBand(dataset, 2), GF_Write, 0, 0, size, size, alpha.ptr(),
                            size, size, type, 0, static_cast<int>(alpha.step[0]));
    }
    GDALClose(dataset);
  }
  out->data = VSIGetMemFileBuffer(memory_path.c_str(), &out->length, TRUE);  // Takes it over.
  if (dataset == nullptr || capture.failed() || out->data == nullptr) {
    out->failure = capture.failed() ? capture.message() : std::string("GDAL failed");
  }
}

// The georeferencing tags GDAL writes for a CRS (GeoTIFF's GeoKeyDirectory, GeoDoubleParams,
// GeoAsciiParams): the same for every tile of a store; the direct encoder copies them.
struct GeoTags {
  std::vector<uint16_t> key_directory;
  std::vector<double> double_params;
  std::string ascii_params;
};

// TIFF tags of the direct layout (TIFF 6.0 and GeoTIFF 1.0 numbers).
constexpr uint16_t kTagModelPixelScale = 33550, kTagModelTiepoint = 33922,
                   kTagGeoKeyDirectory = 34735, kTagGeoDoubleParams = 34736,
                   kTagGeoAsciiParams = 34737;

// The GeoTIFF tags of `file`, a classic little-endian TIFF GDAL wrote for a tile of `settings`
// with geotransform `gt`, when its first directory holds exactly the tags the direct encoder
// writes, with the values it writes (so its files and GDAL's carry the same header); nullopt
// otherwise (a CRS or GDAL version that writes more, e.g. metadata): that CRS goes through GDAL.
std::optional<GeoTags> DirectGeoTagsOf(const GByte* file, size_t size, const double gt[6],
                                       const TileWriteSettings& settings, int tile_size,
                                       int block) {
  const auto u16 = [&](size_t at) { return static_cast<uint16_t>(file[at] | (file[at + 1] << 8)); };
  const auto u32 = [&](size_t at) {
    return static_cast<uint32_t>(file[at]) | (static_cast<uint32_t>(file[at + 1]) << 8) |
           (static_cast<uint32_t>(file[at + 2]) << 16) |
           (static_cast<uint32_t>(file[at + 3]) << 24);
  };
  if (size < 8 || file[0] != 'I' || file[1] != 'I' || u16(2) != 42) return std::nullopt;
  const size_t ifd = u32(4);
  if (ifd + 2 > size) return std::nullopt;
  const size_t entries = u16(ifd);
  if (ifd + 2 + 12 * entries + 4 > size) return std::nullopt;
  struct Entry {
    uint16_t type = 0;
    uint32_t count = 0;
    size_t at = 0;  // Offset of the values in the file.
  };
  std::map<uint16_t, Entry> tags;
  for (size_t k = 0; k < entries; ++k) {
    const size_t e = ifd + 2 + 12 * k;
    Entry entry{u16(e + 2), u32(e + 4), 0};
    size_t unit = 0;
    switch (entry.type) {
      case 1:
      case 2:
        unit = 1;
        break;  // BYTE, ASCII
      case 3:
        unit = 2;
        break;  // SHORT
      case 4:
        unit = 4;
        break;  // LONG
      case 12:
        unit = 8;
        break;  // DOUBLE
      default:
        return std::nullopt;
    }
    const size_t bytes = unit * entry.count;
    entry.at = bytes <= 4 ? e + 8 : u32(e + 8);
    if (entry.at + bytes > size) return std::nullopt;
    tags[u16(e)] = entry;
  }
  const auto shorts = [&](uint16_t tag) {
    std::vector<uint32_t> values;
    const auto it = tags.find(tag);
    if (it == tags.end() || (it->second.type != 3 && it->second.type != 4)) return values;
    for (uint32_t i = 0; i < it->second.count; ++i) {
      values.push_back(it->second.type == 3 ? u16(it->second.at + 2 * i)
                                            : u32(it->second.at + 4 * i));
    }
    return values;
  };
  const auto doubles = [&](uint16_t tag) {
    std::vector<double> values;
    const auto it = tags.find(tag);
    if (it == tags.end() || it->second.type != 12) return values;
    values.resize(it->second.count);
    std::memcpy(values.data(), file + it->second.at, 8 * values.size());
    return values;
  };
  const uint32_t bits = settings.type == PixelType::kUInt16 ? 16 : 8;
  const uint32_t n = static_cast<uint32_t>(tile_size), b = static_cast<uint32_t>(block);
  const uint32_t blocks = 2 * (n / b) * (n / b);
  using V = std::vector<uint32_t>;
  const bool layout =
      shorts(256) == V{n} && shorts(257) == V{n} && shorts(258) == V{bits, bits} &&
      shorts(259) == V{50000} && shorts(262) == V{1} && shorts(277) == V{2} &&
      shorts(284) == V{2} && shorts(317) == V{2} && shorts(322) == V{b} && shorts(323) == V{b} &&
      shorts(324).size() == blocks && shorts(325).size() == blocks && shorts(338) == V{2} &&
      shorts(339) == V{1, 1} &&
      doubles(kTagModelPixelScale) == std::vector<double>{gt[1], -gt[5], 0.0} &&
      doubles(kTagModelTiepoint) == std::vector<double>{0.0, 0.0, 0.0, gt[0], gt[3], 0.0} &&
      gt[2] == 0.0 && gt[4] == 0.0 && tags.count(kTagGeoKeyDirectory) &&
      tags.at(kTagGeoKeyDirectory).type == 3;
  const std::set<uint16_t> known = {256,
                                    257,
                                    258,
                                    259,
                                    262,
                                    277,
                                    284,
                                    317,
                                    322,
                                    323,
                                    324,
                                    325,
                                    338,
                                    339,
                                    kTagModelPixelScale,
                                    kTagModelTiepoint,
                                    kTagGeoKeyDirectory,
                                    kTagGeoDoubleParams,
                                    kTagGeoAsciiParams};
  for (const auto& [tag, entry] : tags) {
    if (!known.count(tag)) return std::nullopt;
  }
  if (!layout) return std::nullopt;
  GeoTags geo;
  for (const uint32_t v : shorts(kTagGeoKeyDirectory)) {
    geo.key_directory.push_back(static_cast<uint16_t>(v));
  }
  geo.double_params = doubles(kTagGeoDoubleParams);
  if (const auto it = tags.find(kTagGeoAsciiParams); it != tags.end()) {
    if (it->second.type != 2 || it->second.count == 0) return std::nullopt;
    // Stored with its terminating NUL, which libtiff adds back.
    geo.ascii_params.assign(reinterpret_cast<const char*>(file + it->second.at),
                            it->second.count - 1);
    if (geo.ascii_params.find('\0') != std::string::npos) return std::nullopt;
  }
  if (tags.count(kTagGeoDoubleParams) && geo.double_params.empty()) return std::nullopt;
  return geo;
}

// GeoTags by CRS, pixel type and tile size; nullopt: GDAL writes that kind of tile otherwise.
std::mutex g_geo_tags_mutex;
std::map<std::string, std::optional<GeoTags>> g_geo_tags;

struct ZstdCompressContextDeleter {
  void operator()(ZSTD_CCtx* context) const { ZSTD_freeCCtx(context); }
};

// The sample every pixel of the block at (x0, y0) holds, if they all hold one (an alpha block
// fully covered or uncovered, the data under it), read as the plane's own type.
template <typename P>
std::optional<P> ConstantBlock(const cv::Mat& plane, int x0, int y0, int block) {
  const P first = plane.ptr<P>(y0)[x0];
  for (int r = 0; r < block; ++r) {
    const P* row = plane.ptr<P>(y0 + r) + x0;
    int c = 0;
#if defined(__SSE2__)
    const __m128i want = sizeof(P) == 1 ? _mm_set1_epi8(static_cast<char>(first))
                                        : _mm_set1_epi16(static_cast<int16_t>(first));
    constexpr int kLanes = 16 / sizeof(P);
    for (; c + kLanes <= block; c += kLanes) {
      const __m128i v = _mm_loadu_si128(reinterpret_cast<const __m128i*>(row + c));
      if (_mm_movemask_epi8(_mm_cmpeq_epi8(v, want)) != 0xFFFF) return std::nullopt;
    }
#endif
    for (; c < block; ++c) {
      if (row[c] != first) return std::nullopt;
    }
  }
  return first;
}

// Compressed blocks of one sample value, by (sample bytes, value, block side, zstd level): a
// block of one value (most alpha blocks, and the data under an uncovered one) compresses to the
// same bytes every time, so it is differenced and compressed once per writer thread.
using ConstantBlockKey = std::tuple<int, uint32_t, int, int>;
constexpr size_t kConstantBlocksKept = 16;

// One band of the tile (`plane`, CV_8U or CV_16U; an 8-bit alpha plane of a UInt16 tile is
// scaled by 257 as GDAL's path does), block by block: rows differenced, compressed, handed to
// libtiff as finished blocks. False with *failure on any error.
// The previous file of a tile being written again: its blocks not in `changed` are copied.
struct BlockSource {
  int fd = -1;
  const TileFileLayout* layout = nullptr;
  BlockMask changed = kAllBlocks;
};

// Copies block `index` (TIFF tile order) of the previous file into the new one. False when it
// cannot (a short read): the caller encodes the block instead.
bool CopyBlock(TIFF* tif, ttile_t index, const BlockSource& source, std::vector<uint8_t>* buffer,
               bool* written) {
  *written = false;
  const uint64_t length = source.layout->lengths[index], offset = source.layout->offsets[index];
  buffer->resize(length);
  if (pread(source.fd, buffer->data(), length, static_cast<off_t>(offset)) !=
      static_cast<ssize_t>(length)) {
    return false;
  }
  *written = TIFFWriteRawTile(tif, index, buffer->data(), static_cast<tmsize_t>(length)) >= 0;
  return true;
}

template <typename T>
bool WriteBandBlocks(TIFF* tif, const cv::Mat& plane, uint16_t sample, int block, int level,
                     const BlockSource& source, std::string* failure) {
  thread_local std::unique_ptr<ZSTD_CCtx, ZstdCompressContextDeleter> context(ZSTD_createCCtx());
  thread_local std::vector<uint8_t> raw, packed;
  thread_local std::vector<uint16_t> widened;
  thread_local std::map<ConstantBlockKey, std::vector<uint8_t>> constant_blocks;
  if (!context) {
    *failure = "libzstd could not make a compression context";
    return false;
  }
  const size_t block_bytes = static_cast<size_t>(block) * block * sizeof(T);
  raw.resize(block_bytes);
  packed.resize(ZSTD_compressBound(block_bytes));
  widened.resize(static_cast<size_t>(block));
  const bool scale = sizeof(T) == 2 && plane.depth() == CV_8U;
  thread_local std::vector<uint8_t> copied;
  const int across = plane.cols / block;
  for (int y0 = 0; y0 < plane.rows; y0 += block) {
    for (int x0 = 0; x0 < plane.cols; x0 += block) {
      const ttile_t index =
          TIFFComputeTile(tif, static_cast<uint32_t>(x0), static_cast<uint32_t>(y0), 0, sample);
      const int bit = (y0 / block) * across + x0 / block;
      if (source.fd >= 0 && !(source.changed >> bit & 1)) {
        bool written = false;
        if (CopyBlock(tif, index, source, &copied, &written)) {
          if (!written) {
            *failure = std::strerror(errno);
            return false;
          }
          if (sample == 0) ++t_blocks_copied;
          continue;
        }
      }
      if (sample == 0) ++t_blocks_encoded;
      std::optional<uint32_t> constant;
      if (scale) {
        if (const auto v = ConstantBlock<uint8_t>(plane, x0, y0, block)) constant = *v * 257u;
      } else if (const auto v = ConstantBlock<T>(plane, x0, y0, block)) {
        constant = *v;
      }
      std::vector<uint8_t>* known = nullptr;
      if (constant) {
        const ConstantBlockKey key{static_cast<int>(sizeof(T)), *constant, block, level};
        const auto it = constant_blocks.find(key);
        if (it != constant_blocks.end()) {
          known = &it->second;
        } else if (constant_blocks.size() < kConstantBlocksKept) {
          known = &constant_blocks[key];  // Filled below.
        }
      }
      if (known && !known->empty()) {
        if (TIFFWriteRawTile(tif, index, known->data(), static_cast<tmsize_t>(known->size())) < 0) {
          *failure = std::strerror(errno);
          return false;
        }
        continue;
      }
      for (int r = 0; r < block; ++r) {
        T* out = reinterpret_cast<T*>(raw.data()) + static_cast<size_t>(r) * block;
        if (scale) {
          const uint8_t* in = plane.ptr<uint8_t>(y0 + r) + x0;
          for (int c = 0; c < block; ++c) widened[c] = static_cast<uint16_t>(in[c] * 257);
          HorizontalDifferencing(widened.data(), reinterpret_cast<uint16_t*>(out), block);
        } else {
          HorizontalDifferencing(plane.ptr<T>(y0 + r) + x0, out, block);
        }
      }
      const size_t length = ZSTD_compressCCtx(context.get(), packed.data(), packed.size(),
                                              raw.data(), block_bytes, level);
      if (ZSTD_isError(length)) {
        *failure = std::string("libzstd: ") + ZSTD_getErrorName(length);
        return false;
      }
      if (known) known->assign(packed.data(), packed.data() + length);
      if (TIFFWriteRawTile(tif, index, packed.data(), static_cast<tmsize_t>(length)) < 0) {
        *failure = std::strerror(errno);
        return false;
      }
    }
  }
  return true;
}

// Writes `tile` to `temp` in the direct layout (TileEncoding::kDirect) with libtiff; its size in
// *bytes. False with *failure on any error (the caller removes `temp`).
// The previous file at `path` opened for copying blocks, if it is the one `reuse` describes
// (same device, inode and size) and has the layout of `blocks` blocks per band; -1 otherwise.
int OpenPreviousTile(const fs::path& path, const TileReuse* reuse, int blocks) {
  if (reuse == nullptr || reuse->previous == nullptr || reuse->changed == kAllBlocks ||
      blocks > 64 || reuse->previous->offsets.size() != 2 * static_cast<size_t>(blocks) ||
      reuse->previous->lengths.size() != reuse->previous->offsets.size()) {
    return -1;
  }
  const int fd = open(path.c_str(), O_RDONLY | O_CLOEXEC);
  if (fd < 0) return -1;
  struct stat st {};
  if (fstat(fd, &st) != 0 || static_cast<uint64_t>(st.st_dev) != reuse->previous->device ||
      static_cast<uint64_t>(st.st_ino) != reuse->previous->inode ||
      static_cast<int64_t>(st.st_size) != reuse->previous->size) {
    close(fd);
    return -1;
  }
  for (size_t k = 0; k < reuse->previous->offsets.size(); ++k) {
    if (reuse->previous->offsets[k] + reuse->previous->lengths[k] >
        static_cast<uint64_t>(st.st_size)) {
      close(fd);
      return -1;
    }
  }
  return fd;
}

bool WriteTileDirect(const fs::path& temp, const fs::path& path, const TileImage& tile,
                     const double gt[6], const TileWriteSettings& settings, const GeoTags& geo,
                     const TileReuse* reuse, TileFileLayout* layout, int64_t* bytes,
                     std::string* failure) {
  GdalErrorCapture capture;  // libtiff's messages go to GDAL's handler once GTiff has run.
  TIFF* tif = TIFFOpen(temp.c_str(), "wl");
  if (tif == nullptr) {
    *failure = capture.failed() ? capture.message() : std::strerror(errno);
    return false;
  }
  // As libgeotiff registers them (GeoTIFF 1.0): counted arrays, the ASCII one NUL-terminated.
  static const TIFFFieldInfo kGeoFields[] = {
      {kTagModelPixelScale, -1, -1, TIFF_DOUBLE, FIELD_CUSTOM, 1, 1,
       const_cast<char*>("ModelPixelScale")},
      {kTagModelTiepoint, -1, -1, TIFF_DOUBLE, FIELD_CUSTOM, 1, 1,
       const_cast<char*>("ModelTiepoint")},
      {kTagGeoKeyDirectory, -1, -1, TIFF_SHORT, FIELD_CUSTOM, 1, 1,
       const_cast<char*>("GeoKeyDirectory")},
      {kTagGeoDoubleParams, -1, -1, TIFF_DOUBLE, FIELD_CUSTOM, 1, 1,
       const_cast<char*>("GeoDoubleParams")},
      {kTagGeoAsciiParams, -1, -1, TIFF_ASCII, FIELD_CUSTOM, 1, 0,
       const_cast<char*>("GeoAsciiParams")},
  };
  const int size = tile.data.cols, block = std::min(kBlockSize, size);
  const bool wide = settings.type == PixelType::kUInt16;
  const uint16_t extra[1] = {EXTRASAMPLE_UNASSALPHA};
  double scale[3] = {gt[1], -gt[5], 0.0};
  double tiepoint[6] = {0.0, 0.0, 0.0, gt[0], gt[3], 0.0};
  bool ok = TIFFMergeFieldInfo(tif, kGeoFields, 5) == 0 &&
            TIFFSetField(tif, TIFFTAG_IMAGEWIDTH, static_cast<uint32_t>(size)) &&
            TIFFSetField(tif, TIFFTAG_IMAGELENGTH, static_cast<uint32_t>(size)) &&
            TIFFSetField(tif, TIFFTAG_BITSPERSAMPLE, wide ? 16 : 8) &&
            TIFFSetField(tif, TIFFTAG_SAMPLESPERPIXEL, 2) &&
            TIFFSetField(tif, TIFFTAG_COMPRESSION, COMPRESSION_ZSTD) &&
            TIFFSetField(tif, TIFFTAG_PHOTOMETRIC, PHOTOMETRIC_MINISBLACK) &&
            TIFFSetField(tif, TIFFTAG_PLANARCONFIG, PLANARCONFIG_SEPARATE) &&
            TIFFSetField(tif, TIFFTAG_PREDICTOR, PREDICTOR_HORIZONTAL) &&
            TIFFSetField(tif, TIFFTAG_TILEWIDTH, static_cast<uint32_t>(block)) &&
            TIFFSetField(tif, TIFFTAG_TILELENGTH, static_cast<uint32_t>(block)) &&
            TIFFSetField(tif, TIFFTAG_EXTRASAMPLES, 1, extra) &&
            TIFFSetField(tif, TIFFTAG_SAMPLEFORMAT, SAMPLEFORMAT_UINT) &&
            TIFFSetField(tif, kTagModelPixelScale, 3, scale) &&
            TIFFSetField(tif, kTagModelTiepoint, 6, tiepoint) &&
            TIFFSetField(tif, kTagGeoKeyDirectory, static_cast<int>(geo.key_directory.size()),
                         geo.key_directory.data());
  if (ok && !geo.double_params.empty()) {
    ok = TIFFSetField(tif, kTagGeoDoubleParams, static_cast<int>(geo.double_params.size()),
                      geo.double_params.data());
  }
  if (ok && !geo.ascii_params.empty()) {
    ok = TIFFSetField(tif, kTagGeoAsciiParams, geo.ascii_params.c_str());
  }
  if (!ok) *failure = "libtiff refused a tag";
  const int level = settings.compression_level;
  const int blocks = (size / block) * (size / block);
  BlockSource source;
  if (ok) {
    source.fd = OpenPreviousTile(path, reuse, blocks);
    source.layout = reuse ? reuse->previous : nullptr;
    source.changed = reuse ? reuse->changed : kAllBlocks;
    ok = wide ? WriteBandBlocks<uint16_t>(tif, tile.data, 0, block, level, source, failure) &&
                    WriteBandBlocks<uint16_t>(tif, tile.alpha, 1, block, level, source, failure)
              : WriteBandBlocks<uint8_t>(tif, tile.data, 0, block, level, source, failure) &&
                    WriteBandBlocks<uint8_t>(tif, tile.alpha, 1, block, level, source, failure);
    if (source.fd >= 0) close(source.fd);
  }
  // Where the blocks went, before TIFFFlush writes the directory (and lets go of the fields).
  if (ok && layout != nullptr) {
    uint64_t* offsets = nullptr;
    uint64_t* lengths = nullptr;
    struct stat st {};
    if (TIFFGetField(tif, TIFFTAG_TILEOFFSETS, &offsets) == 1 &&
        TIFFGetField(tif, TIFFTAG_TILEBYTECOUNTS, &lengths) == 1 && offsets && lengths &&
        fstat(TIFFFileno(tif), &st) == 0) {
      layout->offsets.assign(offsets, offsets + 2 * blocks);
      layout->lengths.assign(lengths, lengths + 2 * blocks);
      layout->device = static_cast<uint64_t>(st.st_dev);
      layout->inode = static_cast<uint64_t>(st.st_ino);
    }
  }
  if (ok && TIFFFlush(tif) != 1) {
    ok = false;
    *failure = capture.failed() ? capture.message() : std::strerror(errno);
  }
  TIFFClose(tif);
  if (!ok) return false;
  std::error_code error;
  *bytes = static_cast<int64_t>(fs::file_size(temp, error));
  if (error) {
    *failure = error.message();
    return false;
  }
  if (layout != nullptr) layout->size = *bytes;
  return true;
}

template <typename T>
void DifferenceRow(const T* in, T* out, int n) {
  if (n <= 0) return;
  out[0] = in[0];
  int i = 1;
#if defined(__SSE2__)
  constexpr int kLanes = 16 / sizeof(T);
  for (; i + kLanes <= n; i += kLanes) {
    const __m128i a = _mm_loadu_si128(reinterpret_cast<const __m128i*>(in + i));
    const __m128i b = _mm_loadu_si128(reinterpret_cast<const __m128i*>(in + i - 1));
    _mm_storeu_si128(reinterpret_cast<__m128i*>(out + i),
                     sizeof(T) == 1 ? _mm_sub_epi8(a, b) : _mm_sub_epi16(a, b));
  }
#endif
  for (; i < n; ++i) out[i] = static_cast<T>(in[i] - in[i - 1]);
}

}  // namespace

void HorizontalDifferencing(const uint8_t* in, uint8_t* out, int n) { DifferenceRow(in, out, n); }
void HorizontalDifferencing(const uint16_t* in, uint16_t* out, int n) { DifferenceRow(in, out, n); }

int64_t DirectTileWrites() { return t_direct_tile_writes; }
int64_t BlocksCopied() { return t_blocks_copied; }
int64_t BlocksEncoded() { return t_blocks_encoded; }

BlockMask BlocksOverlapping(const cv::Rect& rect, int tile_size) {
  const int block = std::min(kBlockSize, tile_size);
  const int across = (tile_size + block - 1) / block;
  if (across * across > 64) return kAllBlocks;
  const cv::Rect r = rect & cv::Rect(0, 0, tile_size, tile_size);
  if (r.empty()) return 0;
  BlockMask mask = 0;
  for (int by = r.y / block; by <= (r.br().y - 1) / block; ++by) {
    for (int bx = r.x / block; bx <= (r.br().x - 1) / block; ++bx) {
      mask |= BlockMask{1} << (by * across + bx);
    }
  }
  return mask;
}

int64_t WriteTileAtomic(const fs::path& path, const TileImage& tile, const double gt[6],
                        const TileWriteSettings& settings, const TileReuse* reuse,
                        TileFileLayout* layout) {
  if (layout != nullptr) *layout = TileFileLayout{};
  const fs::path temp = TemporaryPathFor(path);
  const int size = tile.data.cols;
  const int block = std::min(kBlockSize, size);
  const bool direct_layout =
      settings.encoding == TileEncoding::kDirect && settings.compression == "ZSTD" &&
      (settings.type == PixelType::kByte || settings.type == PixelType::kUInt16) &&
      std::endian::native == std::endian::little && size % block == 0 &&
      tile.data.depth() == CvDepthOf(settings.type) && tile.alpha.depth() == CV_8U;
  const std::string key =
      settings.crs_wkt + "|" + GdalTypeNameOf(settings.type) + "|" + std::to_string(size);
  std::optional<GeoTags> geo;
  bool known = false;
  if (direct_layout) {
    const std::lock_guard<std::mutex> lock(g_geo_tags_mutex);
    const auto it = g_geo_tags.find(key);
    if (it != g_geo_tags.end()) {
      known = true;
      geo = it->second;
    }
  }
  std::string failure;
  int64_t length = 0;
  if (geo) {
    if (WriteTileDirect(temp, path, tile, gt, settings, *geo, reuse, layout, &length, &failure)) {
      ++t_direct_tile_writes;
    }
  } else {
    GdalEncoded encoded;
    EncodeWithGdal(tile, gt, settings, &encoded);
    failure = encoded.failure;
    if (failure.empty()) {
      if (direct_layout && !known) {
        // The first tile of its kind: GDAL's header tells what the direct encoder copies.
        std::optional<GeoTags> tags =
            DirectGeoTagsOf(encoded.data, encoded.length, gt, settings, size, block);
        const std::lock_guard<std::mutex> lock(g_geo_tags_mutex);
        g_geo_tags.emplace(key, std::move(tags));
      }
      std::ofstream out(temp, std::ios::binary | std::ios::trunc);
      out.write(reinterpret_cast<const char*>(encoded.data),
                static_cast<std::streamsize>(encoded.length));
      out.close();  // A file system may report a write error only here.
      if (!out) failure = std::strerror(errno);
      length = static_cast<int64_t>(encoded.length);
    }
  }
  if (!failure.empty()) {
    std::error_code ignored;
    fs::remove(temp, ignored);
    throw OutputError("cannot write tile " + path.string() + ": " + failure +
                      ". Fix: free disk space or check the folder's permissions; the published "
                      "store is unchanged");
  }
  RenameOrThrow(temp, path, settings.durable);
  return length;
}

namespace {

thread_local int64_t t_direct_tile_reads = 0;

#if defined(__SSE2__)
// Byte 15 of v in all 16 bytes.
inline __m128i BroadcastByte15(__m128i v) {
  const __m128i pairs = _mm_unpackhi_epi8(v, v);          // 16-bit lanes (b8 b8) .. (b15 b15)
  const __m128i high = _mm_shufflehi_epi16(pairs, 0xFF);  // lanes 4-7: (b15 b15)
  return _mm_unpackhi_epi64(high, high);                  // every lane
}
// 16-bit lane 7 of v in all 8 lanes.
inline __m128i BroadcastLane7(__m128i v) {
  const __m128i high = _mm_shufflehi_epi16(v, 0xFF);
  return _mm_unpackhi_epi64(high, high);
}
#endif

// The whole file in memory: read in one call, and GDAL then parses the same bytes the blocks are
// decoded from, so a newer version of the tile renamed over this one meanwhile cannot mix in.
// Returns an empty string, or what failed. A file over `max_bytes` is not read (a tile cannot be
// that large; a damaged store must not make a read-back take the memory).
std::string ReadWholeFile(const fs::path& path, size_t max_bytes, std::vector<GByte>* bytes) {
  const int fd = ::open(path.c_str(), O_RDONLY | O_CLOEXEC);
  if (fd < 0) return std::strerror(errno);
  std::string failure;
  struct stat info {};
  if (::fstat(fd, &info) != 0) {
    failure = std::strerror(errno);
  } else if (static_cast<uint64_t>(info.st_size) > max_bytes) {
    failure = std::to_string(info.st_size) + " bytes, more than a tile of this store can be";
  } else {
    bytes->resize(static_cast<size_t>(info.st_size));
    size_t done = 0;
    while (done < bytes->size()) {
      const ssize_t got = ::read(fd, bytes->data() + done, bytes->size() - done);
      if (got < 0 && errno == EINTR) continue;
      if (got <= 0) {
        failure = got < 0 ? std::strerror(errno) : "the file ended early";
        break;
      }
      done += static_cast<size_t>(got);
    }
  }
  ::close(fd);
  return failure;
}

struct ZstdContextDeleter {
  void operator()(ZSTD_DCtx* context) const { ZSTD_freeDCtx(context); }
};

bool ParseUnsigned(const char* text, uint64_t* value) {
  if (text == nullptr) return false;
  const char* end = text + std::strlen(text);
  const auto [last, error] = std::from_chars(text, end, *value);
  return error == std::errc() && last == end;
}

// True when the dataset's samples are laid out as WriteTileAtomic writes them by default and the
// direct decoder knows: ZSTD, horizontal predictor, one plane per band, whole bytes.
bool IsDirectLayout(GDALDatasetH dataset, const std::vector<GByte>& file, PixelType type) {
  const auto item = [&](const char* key) {
    const char* value = GDALGetMetadataItem(dataset, key, "IMAGE_STRUCTURE");
    return std::string(value ? value : "");
  };
  if (type != PixelType::kByte && type != PixelType::kUInt16) return false;
  if (item("COMPRESSION") != "ZSTD" || item("PREDICTOR") != "2" || item("INTERLEAVE") != "BAND" ||
      !item("NBITS").empty()) {
    return false;
  }
  // 16-bit samples are stored in the file's byte order; the decoder takes them as they are.
  if (type == PixelType::kUInt16 && (std::endian::native != std::endian::little ||
                                     file.size() < 2 || file[0] != 'I' || file[1] != 'I')) {
    return false;
  }
  return true;
}

// Decodes band `band_index` of a direct-layout dataset into `out` (the tile's size, CV_8U or
// CV_16U) from the file's bytes: each block's ZSTD frame decompressed, then its rows summed back
// (the predictor undone), the part inside the tile copied. False when anything is not as
// expected (a block missing or out of the file, a frame that does not decompress to the block's
// size); the caller then lets GDAL decode the tile.
bool DecodeBandDirect(GDALDatasetH dataset, int band_index, const std::vector<GByte>& file,
                      cv::Mat* out) {
  GDALRasterBandH band = GDALGetRasterBand(dataset, band_index);
  const bool wide = out->depth() == CV_16U;
  if (band == nullptr || GDALGetRasterDataType(band) != (wide ? GDT_UInt16 : GDT_Byte)) {
    return false;
  }
  int block_w = 0, block_h = 0;
  GDALGetBlockSize(band, &block_w, &block_h);
  if (block_w <= 0 || block_h <= 0) return false;
  const size_t sample = wide ? 2 : 1;
  const size_t block_bytes = static_cast<size_t>(block_w) * block_h * sample;
  thread_local std::vector<uint8_t> block;
  thread_local std::unique_ptr<ZSTD_DCtx, ZstdContextDeleter> context(ZSTD_createDCtx());
  if (!context) return false;
  block.resize(block_bytes);
  const int rows = out->rows, cols = out->cols;
  for (int by = 0; by * block_h < rows; ++by) {
    for (int bx = 0; bx * block_w < cols; ++bx) {
      char key[64];
      uint64_t offset = 0, size = 0;
      std::snprintf(key, sizeof(key), "BLOCK_OFFSET_%d_%d", bx, by);
      if (!ParseUnsigned(GDALGetMetadataItem(band, key, "TIFF"), &offset)) return false;
      std::snprintf(key, sizeof(key), "BLOCK_SIZE_%d_%d", bx, by);
      if (!ParseUnsigned(GDALGetMetadataItem(band, key, "TIFF"), &size)) return false;
      if (offset == 0 || size == 0 || offset > file.size() || size > file.size() - offset) {
        return false;
      }
      const size_t got =
          ZSTD_decompressDCtx(context.get(), block.data(), block_bytes, file.data() + offset, size);
      if (ZSTD_isError(got) || got != block_bytes) return false;
      const int x0 = bx * block_w, y0 = by * block_h;
      const int width = std::min(block_w, cols - x0), height = std::min(block_h, rows - y0);
      for (int r = 0; r < height; ++r) {
        uint8_t* source = block.data() + static_cast<size_t>(r) * block_w * sample;
        uint8_t* target = out->ptr<uint8_t>(y0 + r) + static_cast<size_t>(x0) * sample;
        std::memcpy(target, source, static_cast<size_t>(width) * sample);
        if (wide) {
          UndoHorizontalDifferencing(reinterpret_cast<uint16_t*>(target), width);
        } else {
          UndoHorizontalDifferencing(target, width);
        }
      }
    }
  }
  return true;
}

// The running sum of a row of 8- or 16-bit samples, wrapping, in place.
template <typename T>
void RunningSum(T* row, int n) {
  int i = 0;
#if defined(__SSE2__)
  // In-register prefix sums of 16 bytes in log steps (the vector plus itself shifted by 1, 2, 4
  // and 8 bytes for 8-bit samples, by 2, 4 and 8 bytes for 16-bit ones), plus the sum carried
  // from before them.
  constexpr int kLanes = 16 / sizeof(T);
  const auto add = [](__m128i x, __m128i y) {
    return sizeof(T) == 1 ? _mm_add_epi8(x, y) : _mm_add_epi16(x, y);
  };
  __m128i carry = _mm_setzero_si128();
  for (; i + kLanes <= n; i += kLanes) {
    __m128i v = _mm_loadu_si128(reinterpret_cast<const __m128i*>(row + i));
    if constexpr (sizeof(T) == 1) v = add(v, _mm_slli_si128(v, 1));
    v = add(v, _mm_slli_si128(v, 2));
    v = add(v, _mm_slli_si128(v, 4));
    v = add(v, _mm_slli_si128(v, 8));
    v = add(v, carry);
    _mm_storeu_si128(reinterpret_cast<__m128i*>(row + i), v);
    carry = sizeof(T) == 1 ? BroadcastByte15(v) : BroadcastLane7(v);
  }
#endif
  T sum = i > 0 ? row[i - 1] : 0;
  for (; i < n; ++i) {
    sum = static_cast<T>(sum + row[i]);
    row[i] = sum;
  }
}

}  // namespace

void UndoHorizontalDifferencing(uint8_t* row, int n) { RunningSum(row, n); }
void UndoHorizontalDifferencing(uint16_t* row, int n) { RunningSum(row, n); }

int64_t DirectTileReads() { return t_direct_tile_reads; }

TileImage ReadTile(const fs::path& path, int tile_size, PixelType type, TilePools* pools,
                   TileDecoding decoding) {
  thread_local std::vector<GByte> file;
  // Four times the samples of both bands uncompressed, and room for headers.
  const size_t sample_bytes = CV_ELEM_SIZE(CvDepthOf(type));
  const size_t max_bytes = 4 * 2 * sample_bytes * tile_size * tile_size + (size_t{16} << 20);
  const std::string read_failure = ReadWholeFile(path, max_bytes, &file);
  if (!read_failure.empty()) {
    throw OutputError("cannot read tile " + path.string() + ": " + read_failure +
                      ". Fix: restore the file or start a new store (--overwrite)");
  }
  const std::string memory_path = "/vsimem/irmosaic_read_" + std::to_string(::getpid()) + "_" +
                                  std::to_string(g_temp_counter.fetch_add(1)) + ".tif";
  VSIFCloseL(VSIFileFromMemBuffer(memory_path.c_str(), file.data(), file.size(), FALSE));
  GdalErrorCapture capture;
  GDALDatasetH dataset =
      GDALOpenEx(memory_path.c_str(), GDAL_OF_RASTER | GDAL_OF_READONLY, nullptr, nullptr, nullptr);
  const auto close = [&] {
    if (dataset) GDALClose(dataset);
    VSIUnlink(memory_path.c_str());
  };
  if (dataset == nullptr || GDALGetRasterXSize(dataset) != tile_size ||
      GDALGetRasterYSize(dataset) != tile_size || GDALGetRasterCount(dataset) != 2) {
    close();
    throw OutputError("cannot read tile " + path.string() + ": " +
                      (capture.failed() ? capture.message() : std::string("not a store tile")) +
                      ". Fix: restore the file or start a new store (--overwrite)");
  }
  // The alpha band comes in the data type, then becomes 0/255.
  TileImage tile = pools ? pools->Blank() : EmptyTile(tile_size, type);
  cv::Mat alpha = pools ? pools->data.Take() : cv::Mat(tile_size, tile_size, CvDepthOf(type));
  CPLErr status = CE_None;
  if (decoding == TileDecoding::kDirect && IsDirectLayout(dataset, file, type) &&
      DecodeBandDirect(dataset, 1, file, &tile.data) &&
      DecodeBandDirect(dataset, 2, file, &alpha)) {
    ++t_direct_tile_reads;
  } else {
    // GDAL fills every sample.
    const GDALDataType gdal_type = GdalTypeOf(type);
    status = GDALRasterIO(GDALGetRasterBand(dataset, 1), GF_Read, 0, 0, tile_size, tile_size,
                          tile.data.ptr(), tile_size, tile_size, gdal_type, 0,
                          static_cast<int>(tile.data.step[0]));
    if (status == CE_None) {
      status = GDALRasterIO(GDALGetRasterBand(dataset, 2), GF_Read, 0, 0, tile_size, tile_size,
                            alpha.ptr(), tile_size, tile_size, gdal_type, 0,
                            static_cast<int>(alpha.step[0]));
    }
  }
  close();
  if (status != CE_None) {
    throw OutputError("cannot read tile " + path.string() + ": " + capture.message() +
                      ". Fix: restore the file or start a new store (--overwrite)");
  }
  cv::compare(alpha, 0, tile.alpha, cv::CMP_GT);  // Into tile.alpha's own buffer.
  return tile;
}

namespace {

// sum / count rounded to nearest, ties to even (as cvRound of the exact float quotient), in
// integers; 0 for count 0. A mean of at most 4 samples never exceeds the largest of them.
inline uint32_t RoundedMean(uint32_t sum, uint32_t count) {
  switch (count) {
    case 4:  // sum = 4q + r: up when r is 3, or r is 2 and q is odd.
      return (sum + 1 + ((sum >> 2) & 1)) >> 2;
    case 2:  // sum = 2q + r: up when r is 1 and q is odd.
      return (sum + ((sum >> 1) & 1)) >> 1;
    case 3:  // A third is never exactly x.5.
      return (sum + 1) / 3;
    case 1:
      return sum;
    default:
      return 0;
  }
}

// HalveTile for integer samples: the same result as the float formula below (the sums of up to
// four samples of up to 16 bits are exact in float, and RoundedMean rounds their quotient as the
// float path does), in one pass instead of nine over float images of the tile's size. Coverage is 0
// or 255 in a store.
template <typename T>
TileImage HalveIntegerTile(const TileImage& tile, TilePools* pools) {
  const int w = tile.data.cols / 2, h = tile.data.rows / 2;
  TileImage out = pools && pools->half_data.Fits(h, w, tile.data.type())
                      ? pools->HalfBlank()
                      : TileImage{cv::Mat(h, w, tile.data.type()), cv::Mat(h, w, CV_8U)};
  for (int y = 0; y < h; ++y) {
    const T* v0 = tile.data.ptr<T>(2 * y);
    const T* v1 = tile.data.ptr<T>(2 * y + 1);
    const uchar* c0 = tile.alpha.ptr<uchar>(2 * y);
    const uchar* c1 = tile.alpha.ptr<uchar>(2 * y + 1);
    T* value = out.data.ptr<T>(y);
    uchar* covered = out.alpha.ptr<uchar>(y);
    const auto one_mean = [&](int x) {
      const int i = 2 * x;
      const uint32_t m00 = c0[i] != 0, m01 = c0[i + 1] != 0, m10 = c1[i] != 0, m11 = c1[i + 1] != 0;
      const uint32_t count = m00 + m01 + m10 + m11;
      const uint32_t sum = m00 * v0[i] + m01 * v0[i + 1] + m10 * v1[i] + m11 * v1[i + 1];
      value[x] = static_cast<T>(RoundedMean(sum, count));
      covered[x] = count == 0 ? 0 : 255;
    };
    int x = 0;
#if CV_SIMD128
    {
      // A vector of outputs at once (8 UInt16 on 32-bit sums, 16 Byte on 16-bit sums) where all
      // the samples under them are covered (a tile's inside): RoundedMean's count-4 case. Other
      // blocks output by output.
      using Samples = std::conditional_t<sizeof(T) == 1, cv::v_uint8x16, cv::v_uint16x8>;
      using Sums = std::conditional_t<sizeof(T) == 1, cv::v_uint16x8, cv::v_uint32x4>;
      constexpr int kOutputs = Samples::nlanes;
      const cv::v_uint8x16 none = cv::v_setzero_u8();
      Sums one;
      if constexpr (sizeof(T) == 1) {
        one = cv::v_setall_u16(1);
      } else {
        one = cv::v_setall_u32(1);
      }
      const auto mean = [&](const Sums& a, const Sums& b, const Sums& c, const Sums& d) {
        const Sums sum = a + b + c + d;
        return (sum + one + ((sum >> 2) & one)) >> 2;
      };
      // Coverage of the 2 x kOutputs samples of both rows under a block: 2 all covered, 0 none
      // (the outside of a partly covered tile), 1 mixed.
      const auto coverage = [&](int i) {
        cv::v_uint8x16 any = none, all = cv::v_setall_u8(255);
        for (int k = i; k < i + 2 * kOutputs; k += 16) {
          const cv::v_uint8x16 a = cv::v_load(c0 + k), b = cv::v_load(c1 + k);
          any = any | a | b;
          all = all & (a != none) & (b != none);
        }
        return cv::v_check_all(all) ? 2 : cv::v_check_any(any != none) ? 1 : 0;
      };
      for (; x + kOutputs <= w; x += kOutputs) {
        const int i = 2 * x;
        const int covered_samples = coverage(i);
        if (covered_samples == 0) {  // RoundedMean's count 0, uncovered.
          std::memset(value + x, 0, kOutputs * sizeof(T));
          std::memset(covered + x, 0, kOutputs);
          continue;
        }
        if (covered_samples == 1) {
          for (int k = x; k < x + kOutputs; ++k) one_mean(k);
          continue;
        }
        Samples e0, o0, e1, o1;
        cv::v_load_deinterleave(v0 + i, e0, o0);
        cv::v_load_deinterleave(v1 + i, e1, o1);
        Sums e0l, e0h, o0l, o0h, e1l, e1h, o1l, o1h;
        cv::v_expand(e0, e0l, e0h);
        cv::v_expand(o0, o0l, o0h);
        cv::v_expand(e1, e1l, e1h);
        cv::v_expand(o1, o1l, o1h);
        cv::v_store(value + x, cv::v_pack(mean(e0l, o0l, e1l, o1l), mean(e0h, o0h, e1h, o1h)));
        std::memset(covered + x, 255, kOutputs);
      }
    }
#endif
    for (; x < w; ++x) one_mean(x);
  }
  return out;
}

}  // namespace

TileImage HalveTile(const TileImage& tile, TilePools* pools) {
  if (tile.data.depth() == CV_16U) return HalveIntegerTile<uint16_t>(tile, pools);
  if (tile.data.depth() == CV_8U) return HalveIntegerTile<uint8_t>(tile, pools);
  cv::Mat covered, values, sum_values, sum_covered;
  tile.alpha.convertTo(covered, CV_32F, 1.0 / 255.0);
  tile.data.convertTo(values, CV_32F);
  values = values.mul(covered);
  const cv::Size half(tile.data.cols / 2, tile.data.rows / 2);
  // INTER_AREA at exactly 1/2 is the 2x2 mean.
  cv::resize(values, sum_values, half, 0, 0, cv::INTER_AREA);
  cv::resize(covered, sum_covered, half, 0, 0, cv::INTER_AREA);
  TileImage out;
  cv::Mat mean;
  cv::divide(sum_values, cv::max(sum_covered, 1e-6f), mean);
  out.alpha = sum_covered > 0.0f;
  mean.setTo(0.0f, ~out.alpha);
  mean.convertTo(out.data, tile.data.depth());  // Rounds to nearest for integer types.
  return out;
}

namespace {

constexpr char kHexDigits[] = "0123456789abcdef";

// 64 lowercase hex digits, four per row: the bits in tile order, first tile first.
std::string BitmapHex(const BlockRows& rows) {
  std::string hex;
  hex.reserve(4 * rows.size());
  for (const uint16_t mask : rows) {
    for (int shift = 12; shift >= 0; shift -= 4) hex += kHexDigits[(mask >> shift) & 0xf];
  }
  return hex;
}

}  // namespace

std::string ManifestToJson(const Manifest& manifest) {
  // Keys in the order written below, "format" first, so a reader's cheap identification (the
  // GDAL driver's Identify reads 1 KiB) sees it; nlohmann::json would sort them ("alpha_max"
  // first, "format" after the WKT and the application state).
  using json = nlohmann::ordered_json;
  json levels = json::array();
  for (size_t level = 0; level < manifest.levels.size(); ++level) {
    // Blocks, not tiles: the manifest is rewritten at every publish, and a list of every tile
    // (~40 bytes each) made that cost grow with the flight (docs/store.md).
    json blocks = json::array();
    for (const auto& [block, rows] : manifest.levels[level].blocks()) {
      blocks.push_back(json::array({block.first, block.second, BitmapHex(rows)}));
    }
    levels.push_back({{"level", level},
                      {"gsd_m", manifest.georef.gsd_m * std::ldexp(1.0, static_cast<int>(level))},
                      {"path_pattern", "tiles/" + std::to_string(level) + "/{row}_{col}.tif"},
                      {"blocks", blocks}});
  }
  const TileBounds bounds = manifest.levels.empty() ? TileBounds{} : manifest.levels[0].bounds();
  const bool painted = !manifest.levels.empty() && !manifest.levels[0].empty();
  const double t = manifest.tile_size, gsd = manifest.georef.gsd_m;
  json pending = json::array();
  for (const FrameRecord& r : manifest.frames_pending) {
    json footprint = json::array();
    for (const Eigen::Vector2d& c : r.footprint_m) footprint.push_back({c.x(), c.y()});
    pending.push_back({{"index", r.index},
                       {"time_s", r.time_s},
                       {"footprint_m", footprint},
                       {"pos_only", r.pos_only},
                       {"residual_px", r.residual_px},
                       {"inliers", r.inliers},
                       {"status", r.status}});
  }
  json owed = json::array();
  for (const TileIndex& tile : manifest.overviews_owed) owed.push_back({tile.first, tile.second});
  json j = {
      {"format", kFormatName},
      {"format_version", kFormatVersion},
      {"generation", manifest.generation},
      {"created_utc", manifest.created_utc},
      {"published_utc", manifest.published_utc},
      {"crs_wkt", manifest.georef.crs_wkt},
      {"origin",
       {{"lat_deg", manifest.georef.origin_lat_deg}, {"lon_deg", manifest.georef.origin_lon_deg}}},
      {"gsd_m", gsd},
      {"pixel_convention", "level-0 pixel (col,row) centred at plane (col*gsd_m, -row*gsd_m)"},
      {"tile_size", manifest.tile_size},
      {"block_size", manifest.block_size},
      {"data_type", GdalTypeNameOf(manifest.type)},
      {"alpha_max", AlphaMaxOf(manifest.type)},
      {"compression", manifest.compression},
      {"vrt", "mosaic.vrt"},
      {"frames",
       {{"path", "frames.gpkg"},
        {"layer", "frames"},
        {"count", manifest.frame_count},
        {"time_min_s", manifest.time_min_s},
        {"time_max_s", manifest.time_max_s},
        {"pending", pending}}},
      {"overview_vrts", manifest.overview_vrts},
      {"level0_vrt", manifest.level0_vrt},
      {"display_range", manifest.display_hi > manifest.display_lo
                            ? nlohmann::json{manifest.display_lo, manifest.display_hi}
                            : nlohmann::json(nullptr)},
      {"levels", levels},
      {"overviews_owed", owed},
  };
  if (painted) {
    // Whole pixels, written as JSON integers (readers accept the reals older stores hold).
    const int64_t ti = manifest.tile_size;
    j["bounds_px"] = {{"col_min", bounds.col0 * ti},
                      {"row_min", bounds.row0 * ti},
                      {"col_max", bounds.col1 * ti},
                      {"row_max", bounds.row1 * ti}};
    j["bounds_m"] = {{"x_min", (bounds.col0 * t - 0.5) * gsd},
                     {"x_max", (bounds.col1 * t - 0.5) * gsd},
                     {"y_min", -(bounds.row1 * t - 0.5) * gsd},
                     {"y_max", -(bounds.row0 * t - 0.5) * gsd}};
  } else {
    j["bounds_px"] = nullptr;
    j["bounds_m"] = nullptr;
  }
  if (manifest.planned_bounds_px) {
    const auto& p = *manifest.planned_bounds_px;
    j["planned_bounds_px"] = {
        {"col_min", p[0]}, {"row_min", p[1]}, {"col_max", p[2]}, {"row_max", p[3]}};
  }
  if (manifest.application_json.empty()) {
    j["application"] = nullptr;
    return j.dump(1) + "\n";
  }
  // The application's state goes in as the text it came as, last (TileStore::SetApplicationState
  // checked that it is JSON): the Mosaicker's is its optimizer window, ~0.4 MB, and parsing it
  // and writing it out again at every publish was ~40 % of the index's time (docs/benchmarks.md,
  // "Session 26").
  std::string text = j.dump(1);  // "{\n \"format\": ...\n}": the closing "\n}" comes off.
  text.resize(text.size() - 2);
  text.reserve(text.size() + manifest.application_json.size() + 24);
  text += ",\n \"application\": ";
  text += manifest.application_json;
  text += "\n}\n";
  return text;
}

namespace {

// A JSON number that must be whole: a float such as 1e30 would overflow a plain get<int64_t>().
int64_t WholeNumber(const nlohmann::json& value, const char* field, const fs::path& path) {
  // An unsigned above INT64_MAX would wrap to a negative number.
  const bool fits =
      !value.is_number_unsigned() || value.get<uint64_t>() <= static_cast<uint64_t>(INT64_MAX);
  if (value.is_number_integer() && fits) return value.get<int64_t>();
  if (value.is_number_float()) {
    const double x = value.get<double>();
    constexpr double kLimit = 9.0e15;  // Below 2^53: every whole double here is exact.
    if (std::isfinite(x) && x == std::floor(x) && std::abs(x) < kLimit) {
      return static_cast<int64_t>(x);
    }
  }
  throw InputError({path.string(), 0, 0, field}, "'" + value.dump() + "' is not a whole number",
                   "restore the store or start a new one (--overwrite)");
}

int64_t InRange(int64_t value, int64_t lo, int64_t hi, const char* field, const fs::path& path) {
  if (value < lo || value > hi) {
    throw InputError({path.string(), 0, 0, field},
                     std::string(field) + " " + std::to_string(value) + " is not in [" +
                         std::to_string(lo) + ", " + std::to_string(hi) + "]",
                     "restore the store or start a new one (--overwrite)");
  }
  return value;
}

// The values every reader divides by, shifts by or allocates from: a manifest edited by hand or
// damaged on disk must be refused here rather than crash a later read (found by the fuzzer).
void CheckManifestRanges(const Manifest& m, const fs::path& path) {
  auto refuse = [&](const char* field, const std::string& problem) {
    throw InputError({path.string(), 0, 0, field}, problem,
                     "restore the store or start a new one (--overwrite)");
  };
  if (m.tile_size < 16 || m.tile_size > 8192 || m.tile_size % 16 != 0) {
    refuse("tile_size",
           "tile_size " + std::to_string(m.tile_size) + " is not a multiple of 16 in [16, 8192]");
  }
  if (m.block_size < 16 || m.block_size > 8192) {
    refuse("block_size", "block_size " + std::to_string(m.block_size) + " is not in [16, 8192]");
  }
  if (!std::isfinite(m.georef.gsd_m) || !(m.georef.gsd_m > 0.0)) {
    refuse("gsd_m", "gsd_m must be a positive number of metres");
  }
  if (!(std::abs(m.georef.origin_lat_deg) <= 90.0) ||
      !(std::abs(m.georef.origin_lon_deg) <= 360.0)) {
    refuse("origin", "the origin is not a latitude/longitude in degrees");
  }
  if (m.generation < 0) refuse("generation", "generation is negative");
  if (m.levels.size() > 17) {  // Level 0 and at most 16 overview levels (TileStoreOptions).
    refuse("levels", std::to_string(m.levels.size()) + " levels; at most 17 are possible");
  }
  // Tile indices times the tile size must stay within int64 pixel arithmetic.
  constexpr int64_t kMaxTileIndex = int64_t{1} << 40;
  for (const LevelTiles& level : m.levels) {
    for (const TileIndex& tile : level.tiles()) {
      if (tile.first < -kMaxTileIndex || tile.first > kMaxTileIndex ||
          tile.second < -kMaxTileIndex || tile.second > kMaxTileIndex) {
        refuse("levels", "tile index [" + std::to_string(tile.first) + ", " +
                             std::to_string(tile.second) + "] is out of range");
      }
    }
  }
}

// A manifest's tiles, all levels together, at most: the store's set costs ~50 bytes a tile, and a
// format-2 block of ~70 bytes of (compact) text names up to 256 tiles.
constexpr int64_t kMaxManifestTiles = int64_t{8} << 20;
// Block indices within +-2^36 keep their tiles within CheckManifestRanges's +-2^40, so a block's
// first pixel (block * 16 * tile_size) stays far inside int64.
constexpr int64_t kMaxBlockIndex = (int64_t{1} << 40) / kVrtBlockTiles;

[[noreturn]] void RefuseField(const std::string& field, const std::string& problem,
                              const fs::path& path) {
  throw InputError({path.string(), 0, 0, field}, problem,
                   "restore the store or start a new one (--overwrite)");
}

// manifest.json's frames.pending (stores written before 2026-12-06 have none).
std::vector<FrameRecord> ReadPendingRecords(const nlohmann::json& pending, const fs::path& path) {
  if (!pending.is_array()) RefuseField("frames.pending", "frames.pending is not an array", path);
  std::vector<FrameRecord> records;
  for (const nlohmann::json& r : pending) {
    FrameRecord record;
    record.index = InRange(WholeNumber(r.at("index"), "frames.pending index", path), 0,
                           int64_t{1} << 53, "frames.pending index", path);
    record.time_s = r.at("time_s").get<double>();
    const nlohmann::json& footprint = r.at("footprint_m");
    if (!footprint.is_array() || footprint.size() != 4) {
      RefuseField("frames.pending", "a footprint is not 4 corners", path);
    }
    for (size_t k = 0; k < 4; ++k) {
      record.footprint_m[k] = {footprint[k].at(0).get<double>(), footprint[k].at(1).get<double>()};
    }
    record.pos_only = r.at("pos_only").get<bool>();
    record.residual_px = r.at("residual_px").get<double>();
    record.inliers = static_cast<int>(InRange(WholeNumber(r.at("inliers"), "inliers", path), 0,
                                              int64_t{1} << 30, "inliers", path));
    record.status = r.at("status").get<std::string>();
    records.push_back(std::move(record));
  }
  return records;
}

void CountTiles(int64_t added, int64_t* total, const std::string& field, const fs::path& path) {
  *total += added;
  if (*total > kMaxManifestTiles) {
    RefuseField(field,
                "the manifest lists more than " + std::to_string(kMaxManifestTiles) + " tiles",
                path);
  }
}

int HexDigitValue(char c) {
  if (c >= '0' && c <= '9') return c - '0';
  if (c >= 'a' && c <= 'f') return c - 'a' + 10;
  return -1;
}

// One format-2 block entry, [block_row, block_col, "<64 hex digits>"], validated: its block
// (not in `seen` yet; added) and its number of tiles.
BlockIndex CheckBlock(const nlohmann::json& entry, const std::string& field, const fs::path& path,
                      std::set<BlockIndex>* seen, int64_t* tiles) {
  if (!entry.is_array() || entry.size() != 3 || !entry[0].is_number() || !entry[1].is_number() ||
      !entry[2].is_string()) {
    RefuseField(
        field,
        "'" + entry.dump().substr(0, 100) + "' is not [block_row, block_col, \"<64 hex digits>\"]",
        path);
  }
  const BlockIndex block = {WholeNumber(entry[0], field.c_str(), path),
                            WholeNumber(entry[1], field.c_str(), path)};
  const std::string name =
      "block [" + std::to_string(block.first) + ", " + std::to_string(block.second) + "]";
  const auto in_range = [](int64_t b) { return b >= -kMaxBlockIndex && b < kMaxBlockIndex; };
  if (!in_range(block.first) || !in_range(block.second)) {
    RefuseField(field, name + " is out of range (block indices lie in [-2^36, 2^36))", path);
  }
  const std::string& hex = entry[2].get_ref<const std::string&>();
  if (hex.size() != 4 * kVrtBlockTiles ||
      !std::all_of(hex.begin(), hex.end(), [](char c) { return HexDigitValue(c) >= 0; })) {
    RefuseField(field, "bitmap \"" + hex.substr(0, 80) + "\" is not 64 lowercase hex digits", path);
  }
  *tiles = 0;
  for (const char c : hex) *tiles += std::popcount(static_cast<unsigned>(HexDigitValue(c)));
  if (*tiles == 0) {
    RefuseField(field, "the bitmap lists no tile (a block is listed only if it holds one)", path);
  }
  if (!seen->insert(block).second) RefuseField(field, name + " is listed twice", path);
  return block;
}

// Inserts the tiles of a checked bitmap: bit i (digit i / 4, from its most significant bit) is
// tile (16 block_row + i / 16, 16 block_col + i % 16) (docs/store.md).
void InsertBlockTiles(const BlockIndex& block, const std::string& hex, LevelTiles* tiles) {
  BlockRows rows{};
  for (size_t digit = 0; digit < hex.size(); ++digit) {
    const auto value = static_cast<unsigned>(HexDigitValue(hex[digit]));
    rows[digit / 4] = static_cast<uint16_t>(rows[digit / 4] | (value << (12 - 4 * (digit % 4))));
  }
  tiles->InsertBlock(block, rows);
}

// The tiles of manifest level `l`: format 1 lists them ("tiles": [[row, col], ...]), format 2
// lists blocks with a bitmap ("blocks"); a level holding the other format's list, or both, is
// refused rather than half read.
LevelTiles ReadLevelTiles(const nlohmann::json& level, size_t l, int64_t format_version,
                          const fs::path& path, int64_t* tiles_total) {
  const std::string field = "levels[" + std::to_string(l) + "]";
  if (!level.is_object()) RefuseField(field, field + " is not an object", path);
  if (level.contains("tiles") && level.contains("blocks")) {
    RefuseField(field, field + " holds both \"tiles\" (format 1) and \"blocks\" (format 2)", path);
  }
  const char* key = format_version >= 2 ? "blocks" : "tiles";
  if (!level.contains(key)) {
    RefuseField(field + "." + key,
                field + "." + key + " is missing (format_version " +
                    std::to_string(format_version) + " lists a level's tiles as \"" + key + "\")",
                path);
  }
  const nlohmann::json& list = level[key];
  if (!list.is_array())
    RefuseField(field + "." + key, field + "." + key + " is not an array", path);
  LevelTiles tiles;
  if (format_version >= 2) {
    // Every entry checked and counted before any tile is held: ~70 bytes of text name up to
    // 256 tiles, so a hostile manifest is refused before it costs memory.
    std::set<BlockIndex> seen;
    std::vector<BlockIndex> blocks(list.size());
    for (size_t k = 0; k < list.size(); ++k) {
      const std::string entry = field + ".blocks[" + std::to_string(k) + "]";
      int64_t count = 0;
      blocks[k] = CheckBlock(list[k], entry, path, &seen, &count);
      CountTiles(count, tiles_total, entry, path);
    }
    for (size_t k = 0; k < list.size(); ++k) {
      InsertBlockTiles(blocks[k], list[k][2].get_ref<const std::string&>(), &tiles);
    }
    return tiles;
  }
  CountTiles(static_cast<int64_t>(list.size()), tiles_total, field + ".tiles", path);
  for (const auto& tile : list) {
    tiles.insert(
        {WholeNumber(tile.at(0), "levels", path), WholeNumber(tile.at(1), "levels", path)});
  }
  return tiles;
}

}  // namespace

Manifest ReadManifest(const fs::path& path) {
  std::ifstream in(path);
  if (!in) {
    throw InputError({path.string(), 0, 0, ""}, "cannot open the store manifest",
                     "give the folder of an irmosaic store (it holds manifest.json)");
  }
  nlohmann::json j;
  try {
    in >> j;
  } catch (const nlohmann::json::exception& e) {
    throw InputError({path.string(), 0, 0, ""},
                     std::string("manifest is not valid JSON: ") + e.what(),
                     "restore the store or start a new one (--overwrite)");
  }
  if (!j.is_object()) {
    throw InputError({path.string(), 0, 0, ""}, "manifest is not a JSON object",
                     "give the folder of an irmosaic store");
  }
  try {
    if (j.value("format", "") != kFormatName) {
      throw InputError({path.string(), 0, 0, "format"}, "not an irmosaic store manifest",
                       "give the folder of an irmosaic store");
    }
    const int64_t format_version =
        j.contains("format_version") ? WholeNumber(j["format_version"], "format_version", path) : 0;
    if (format_version > kFormatVersion) {
      throw InputError({path.string(), 0, 0, "format_version"},
                       "store format version " + std::to_string(format_version) +
                           " is newer than this program's " + std::to_string(kFormatVersion),
                       "use a newer irmosaic");
    }
    Manifest m;
    m.generation = WholeNumber(j.at("generation"), "generation", path);
    m.created_utc = j.value("created_utc", "");
    m.published_utc = j.value("published_utc", "");
    m.georef.crs_wkt = j.at("crs_wkt").get<std::string>();
    m.georef.origin_lat_deg = j.at("origin").at("lat_deg").get<double>();
    m.georef.origin_lon_deg = j.at("origin").at("lon_deg").get<double>();
    m.georef.gsd_m = j.at("gsd_m").get<double>();
    m.tile_size = static_cast<int>(
        InRange(WholeNumber(j.at("tile_size"), "tile_size", path), 16, 8192, "tile_size", path));
    m.block_size = j.contains("block_size")
                       ? static_cast<int>(InRange(WholeNumber(j["block_size"], "block_size", path),
                                                  16, 8192, "block_size", path))
                       : kBlockSize;
    m.type = PixelTypeFromName(j.at("data_type").get<std::string>());
    m.compression = j.value("compression", "ZSTD");
    const auto& frames = j.at("frames");
    m.frame_count = frames.contains("count") ? WholeNumber(frames["count"], "count", path) : 0;
    m.time_min_s = frames.value("time_min_s", 0.0);
    m.time_max_s = frames.value("time_max_s", 0.0);
    if (frames.contains("pending")) m.frames_pending = ReadPendingRecords(frames["pending"], path);
    m.overview_vrts = j.value("overview_vrts", std::vector<std::string>{});
    m.level0_vrt = j.value("level0_vrt", std::string());
    if (j.contains("display_range") && j["display_range"].is_array()) {
      m.display_lo = j["display_range"].at(0).get<double>();
      m.display_hi = j["display_range"].at(1).get<double>();
    }
    const nlohmann::json& levels = j.at("levels");
    if (!levels.is_array()) RefuseField("levels", "levels is not an array", path);
    int64_t tiles_total = 0;
    for (size_t l = 0; l < levels.size(); ++l) {
      m.levels.push_back(ReadLevelTiles(levels[l], l, format_version, path, &tiles_total));
    }
    if (j.contains("overviews_owed")) {
      const nlohmann::json& owed = j["overviews_owed"];
      if (!owed.is_array()) RefuseField("overviews_owed", "overviews_owed is not an array", path);
      for (const nlohmann::json& tile : owed) {
        if (!tile.is_array() || tile.size() != 2) {
          RefuseField("overviews_owed", "an entry of overviews_owed is not [row, col]", path);
        }
        m.overviews_owed.emplace_back(WholeNumber(tile[0], "overviews_owed", path),
                                      WholeNumber(tile[1], "overviews_owed", path));
      }
    }
    if (j.contains("application") && !j["application"].is_null()) {
      m.application_json = j["application"].dump();
    }
    if (j.contains("planned_bounds_px") && !j["planned_bounds_px"].is_null()) {
      const auto& p = j["planned_bounds_px"];
      std::array<int64_t, 4> planned{};
      const char* const keys[4] = {"col_min", "row_min", "col_max", "row_max"};
      for (int k = 0; k < 4; ++k) {
        planned[k] = InRange(WholeNumber(p.at(keys[k]), "planned_bounds_px", path),
                             -(int64_t{1} << 40), int64_t{1} << 40, "planned_bounds_px", path);
      }
      if (planned[0] >= planned[2] || planned[1] >= planned[3]) {
        throw InputError({path.string(), 0, 0, "planned_bounds_px"}, "the planned extent is empty",
                         "remove planned_bounds_px or restore the manifest");
      }
      m.planned_bounds_px = planned;
    }
    CheckManifestRanges(m, path);
    return m;
  } catch (const InputError&) {
    throw;
  } catch (const std::exception& e) {
    throw InputError({path.string(), 0, 0, ""}, std::string("manifest is incomplete: ") + e.what(),
                     "restore the store or start a new one (--overwrite)");
  }
}

BlockIndex BlockOf(const TileIndex& tile) {
  auto floor_div = [](int64_t v) {
    return v >= 0 ? v / kVrtBlockTiles : -((-v + kVrtBlockTiles - 1) / kVrtBlockTiles);
  };
  return {floor_div(tile.first), floor_div(tile.second)};
}

std::string BlockVrtName(const BlockIndex& block) {
  return "block_r" + std::to_string(block.first) + "_c" + std::to_string(block.second) + ".vrt";
}

int TilesIn(const BlockRows& rows) {
  int n = 0;
  for (const uint16_t mask : rows) n += std::popcount(mask);
  return n;
}

namespace {

// Bit of tile `tile` in its block `block`: row index and column mask.
std::pair<size_t, uint16_t> BitOf(const TileIndex& tile, const BlockIndex& block) {
  const int64_t row = tile.first - block.first * kVrtBlockTiles;
  const int64_t col = tile.second - block.second * kVrtBlockTiles;
  return {static_cast<size_t>(row), static_cast<uint16_t>(0x8000u >> col)};
}

}  // namespace

bool LevelTiles::insert(const TileIndex& tile) {
  const BlockIndex block = BlockOf(tile);
  const auto [row, bit] = BitOf(tile, block);
  uint16_t& mask = blocks_[block][row];
  if (mask & bit) return false;
  mask = static_cast<uint16_t>(mask | bit);
  ++size_;
  return true;
}

bool LevelTiles::erase(const TileIndex& tile) {
  const BlockIndex block = BlockOf(tile);
  const auto it = blocks_.find(block);
  if (it == blocks_.end()) return false;
  const auto [row, bit] = BitOf(tile, block);
  uint16_t& mask = it->second[row];
  if (!(mask & bit)) return false;
  mask = static_cast<uint16_t>(mask & ~bit);
  --size_;
  if (TilesIn(it->second) == 0) blocks_.erase(it);
  return true;
}

bool LevelTiles::contains(const TileIndex& tile) const {
  const BlockIndex block = BlockOf(tile);
  const auto it = blocks_.find(block);
  if (it == blocks_.end()) return false;
  const auto [row, bit] = BitOf(tile, block);
  return (it->second[row] & bit) != 0;
}

void LevelTiles::InsertBlock(const BlockIndex& block, const BlockRows& rows) {
  if (TilesIn(rows) == 0) return;
  BlockRows& held = blocks_[block];
  for (size_t r = 0; r < held.size(); ++r) {
    size_ += static_cast<size_t>(std::popcount(static_cast<uint16_t>(rows[r] & ~held[r])));
    held[r] = static_cast<uint16_t>(held[r] | rows[r]);
  }
}

std::vector<TileIndex> LevelTiles::tiles() const {
  std::vector<TileIndex> out;
  out.reserve(size_);
  for (const auto& [block, rows] : blocks_) {
    for (int64_t r = 0; r < kVrtBlockTiles; ++r) {
      for (int64_t c = 0; c < kVrtBlockTiles; ++c) {
        if (rows[static_cast<size_t>(r)] & (0x8000u >> c)) {
          out.emplace_back(block.first * kVrtBlockTiles + r, block.second * kVrtBlockTiles + c);
        }
      }
    }
  }
  return out;
}

TileBounds LevelTiles::bounds() const {
  if (blocks_.empty()) return {};
  TileBounds b{INT64_MAX, INT64_MIN, INT64_MAX, INT64_MIN};
  for (const auto& [block, rows] : blocks_) {
    uint16_t columns = 0;
    for (int64_t r = 0; r < kVrtBlockTiles; ++r) {
      const uint16_t mask = rows[static_cast<size_t>(r)];
      if (!mask) continue;
      columns = static_cast<uint16_t>(columns | mask);
      b.row0 = std::min(b.row0, block.first * kVrtBlockTiles + r);
      b.row1 = std::max(b.row1, block.first * kVrtBlockTiles + r + 1);
    }
    // Column c is bit 15 - c: the first column is the highest set bit, the last the lowest.
    const int64_t first = std::countl_zero(columns), last = 15 - std::countr_zero(columns);
    b.col0 = std::min(b.col0, block.second * kVrtBlockTiles + first);
    b.col1 = std::max(b.col1, block.second * kVrtBlockTiles + last + 1);
  }
  return b;
}

namespace {

// GDAL's block size for a VRT band that names none: what a block VRT reports when opened.
constexpr int64_t kVrtDefaultBlockSize = 128;

// The head of a VRT of `width` x `height` pixels with geotransform `gt`; the generation only in
// mosaic.vrt (block and overview VRTs are rewritten only when they change).
void VrtHead(const Manifest& manifest, int level, bool with_generation, const double gt[6],
             int64_t width, int64_t height, std::ostringstream* xml) {
  *xml << "<VRTDataset rasterXSize=\"" << width << "\" rasterYSize=\"" << height << "\">\n"
       << "  <SRS dataAxisToSRSAxisMapping=\"1,2\">" << XmlEscape(manifest.georef.crs_wkt)
       << "</SRS>\n"
       << "  <GeoTransform>" << FormatGeoTransform(gt) << "</GeoTransform>\n"
       << "  <Metadata>\n";
  if (with_generation) {
    *xml << "    <MDI key=\"IRMOSAIC_GENERATION\">" << manifest.generation << "</MDI>\n";
  }
  *xml << "    <MDI key=\"IRMOSAIC_LEVEL\">" << level << "</MDI>\n  </Metadata>\n";
}

// A source of `size_x` x `size_y` pixels (file `path`, block size `block`) whose top-left pixel
// sits at (dx, dy) of a VRT of width x height: clipped to the VRT.
void VrtSource(const std::string& path, int band, const std::string& type, int64_t size_x,
               int64_t size_y, int64_t block, int64_t dx, int64_t dy, int64_t width, int64_t height,
               std::ostringstream* xml) {
  const int64_t sx = std::max<int64_t>(0, -dx), sy = std::max<int64_t>(0, -dy);
  const int64_t w = std::min(size_x - sx, width - std::max<int64_t>(0, dx));
  const int64_t h = std::min(size_y - sy, height - std::max<int64_t>(0, dy));
  if (w <= 0 || h <= 0) return;
  *xml << "    <SimpleSource>\n      <SourceFilename relativeToVRT=\"1\">" << XmlEscape(path)
       << "</SourceFilename>\n"
       << "      <SourceBand>" << band << "</SourceBand>\n"
       << "      <SourceProperties RasterXSize=\"" << size_x << "\" RasterYSize=\"" << size_y
       << "\" DataType=\"" << type << "\" BlockXSize=\"" << block << "\" BlockYSize=\"" << block
       << "\"/>\n"
       << "      <SrcRect xOff=\"" << sx << "\" yOff=\"" << sy << "\" xSize=\"" << w
       << "\" ySize=\"" << h << "\"/>\n"
       << "      <DstRect xOff=\"" << std::max<int64_t>(0, dx) << "\" yOff=\""
       << std::max<int64_t>(0, dy) << "\" xSize=\"" << w << "\" ySize=\"" << h << "\"/>\n"
       << "    </SimpleSource>\n";
}

void VrtBandHead(int band, const std::string& type, std::ostringstream* xml) {
  *xml << "  <VRTRasterBand dataType=\"" << type << "\" band=\"" << band << "\">\n"
       << "    <ColorInterp>" << (band == 1 ? "Gray" : "Alpha") << "</ColorInterp>\n";
}

}  // namespace

TileBounds VrtBounds(const TileBounds& painted) {
  // floor(v / step) * step and its ceiling, for signed v and step a power of two.
  auto grow = [](int64_t lo, int64_t hi, int64_t* out_lo, int64_t* out_hi) {
    int64_t step = 1;
    while (2 * step * 16 <= hi - lo) step *= 2;
    *out_lo = lo >= 0 ? lo / step * step : -((-lo + step - 1) / step) * step;
    *out_hi = hi >= 0 ? (hi + step - 1) / step * step : -(-hi / step) * step;
  };
  TileBounds b;
  grow(painted.row0, painted.row1, &b.row0, &b.row1);
  grow(painted.col0, painted.col1, &b.col0, &b.col1);
  return b;
}

std::string BuildBlockVrt(const Manifest& manifest, int level, const BlockIndex& block) {
  const int64_t t = manifest.tile_size;
  const int64_t side = kVrtBlockTiles * t;
  const TileIndex first = {block.first * kVrtBlockTiles, block.second * kVrtBlockTiles};
  const std::string type = GdalTypeNameOf(manifest.type);
  double gt[6];
  TileGeoTransform(manifest.georef.gsd_m, manifest.tile_size, level, first, gt);
  std::ostringstream xml;
  VrtHead(manifest, level, false, gt, side, side, &xml);
  const auto& blocks = manifest.levels[level].blocks();
  const auto found = blocks.find(block);
  const BlockRows rows = found == blocks.end() ? BlockRows{} : found->second;
  for (int band = 1; band <= 2; ++band) {
    VrtBandHead(band, type, &xml);
    for (int64_t r = 0; r < kVrtBlockTiles; ++r) {
      for (int64_t c = 0; c < kVrtBlockTiles; ++c) {
        if (!(rows[static_cast<size_t>(r)] & (0x8000u >> c))) continue;
        VrtSource(std::to_string(first.first + r) + "_" + std::to_string(first.second + c) + ".tif",
                  band, type, t, t, std::min<int64_t>(kBlockSize, t), c * t, r * t, side, side,
                  &xml);
      }
    }
    xml << "  </VRTRasterBand>\n";
  }
  xml << "</VRTDataset>\n";
  return xml.str();
}

namespace {

// A level's size in its own pixels over `bounds` and the geotransform of its first pixel. Every
// level spans the same ground as level 0 (GDAL requires it of overviews); T is a multiple of
// 2^level, so these are whole pixels.
struct LevelGeometry {
  int64_t x0 = 0, y0 = 0, width = 0, height = 0;
  double gt[6] = {};
};

LevelGeometry GeometryOf(const Manifest& manifest, int level, const TileBounds& bounds) {
  const int64_t t = manifest.tile_size;
  const int64_t scale = int64_t{1} << level;
  LevelGeometry g;
  g.x0 = bounds.col0 * t / scale;
  g.y0 = bounds.row0 * t / scale;
  g.width = (bounds.col1 - bounds.col0) * t / scale;
  g.height = (bounds.row1 - bounds.row0) * t / scale;
  TileGeoTransform(manifest.georef.gsd_m, manifest.tile_size, 0, {bounds.row0, bounds.col0}, g.gt);
  g.gt[1] *= static_cast<double>(scale);
  g.gt[5] *= static_cast<double>(scale);
  return g;
}

void VrtOverviews(const std::vector<std::string>& overview_paths, int band,
                  std::ostringstream* xml) {
  for (const std::string& overview : overview_paths) {
    *xml << "    <Overview><SourceFilename relativeToVRT=\"1\">" << XmlEscape(overview)
         << "</SourceFilename><SourceBand>" << band << "</SourceBand></Overview>\n";
  }
}

}  // namespace

std::string LevelVrtPath(int level, const TileBounds& bounds) {
  const std::string extent = "_r" + std::to_string(bounds.row0) + "_c" +
                             std::to_string(bounds.col0) + "_" +
                             std::to_string(bounds.row1 - bounds.row0) + "x" +
                             std::to_string(bounds.col1 - bounds.col0) + ".vrt";
  if (level == 0) return "tiles/level0" + extent;
  return "tiles/" + std::to_string(level) + "/overview" + extent;
}

std::string BuildLevelVrt(const Manifest& manifest, int level, const TileBounds& bounds) {
  const LevelGeometry g = GeometryOf(manifest, level, bounds);
  const std::string type = GdalTypeNameOf(manifest.type);
  // Level 0's VRT sits in tiles/, the overviews' beside their tiles.
  const std::string prefix = level == 0 ? "0/" : "";
  const int64_t side = kVrtBlockTiles * manifest.tile_size;
  std::ostringstream xml;
  VrtHead(manifest, level, false, g.gt, g.width, g.height, &xml);
  const auto& blocks = manifest.levels[level].blocks();
  for (int band = 1; band <= 2; ++band) {
    VrtBandHead(band, type, &xml);
    for (const auto& [block, rows] : blocks) {
      // Block origin in this level's pixels, relative to the VRT; clipped to the VRT.
      VrtSource(prefix + BlockVrtName(block), band, type, side, side, kVrtDefaultBlockSize,
                block.second * side - g.x0, block.first * side - g.y0, g.width, g.height, &xml);
    }
    xml << "  </VRTRasterBand>\n";
  }
  xml << "</VRTDataset>\n";
  return xml.str();
}

std::string BuildMosaicVrt(const Manifest& manifest, const TileBounds& bounds,
                           const std::string& level0_path,
                           const std::vector<std::string>& overview_paths) {
  const LevelGeometry g = GeometryOf(manifest, 0, bounds);
  const std::string type = GdalTypeNameOf(manifest.type);
  std::ostringstream xml;
  VrtHead(manifest, 0, true, g.gt, g.width, g.height, &xml);
  for (int band = 1; band <= 2; ++band) {
    VrtBandHead(band, type, &xml);
    VrtOverviews(overview_paths, band, &xml);
    VrtSource(level0_path, band, type, g.width, g.height, kVrtDefaultBlockSize, 0, 0, g.width,
              g.height, &xml);
    xml << "  </VRTRasterBand>\n";
  }
  xml << "</VRTDataset>\n";
  return xml.str();
}

namespace {

OGRSpatialReference SpatialReferenceOf(const std::string& wkt) {
  OGRSpatialReference srs;
  srs.importFromWkt(wkt.c_str());
  srs.SetAxisMappingStrategy(OAMS_TRADITIONAL_GIS_ORDER);
  return srs;
}

void FillFeature(OGRFeature* feature, const FrameRecord& record, const OGRSpatialReference* srs) {
  feature->SetFID(record.index + 1);  // GeoPackage FIDs are positive.
  feature->SetField("frame_index", static_cast<GIntBig>(record.index));
  feature->SetField("time_s", record.time_s);
  feature->SetField("pos_only", record.pos_only ? 1 : 0);
  feature->SetField("residual_px", record.residual_px);
  feature->SetField("inliers", record.inliers);
  feature->SetField("status", record.status.c_str());
  OGRLinearRing ring;
  for (int c = 0; c <= 4; ++c) {
    ring.addPoint(record.footprint_m[c % 4].x(), record.footprint_m[c % 4].y());
  }
  OGRPolygon polygon;
  polygon.addRing(&ring);
  polygon.assignSpatialReference(const_cast<OGRSpatialReference*>(srs));
  feature->SetGeometry(&polygon);
}

// The SQLite settings of one frames.gpkg connection (GDAL reads them when it opens the file),
// set for this thread only and cleared when the scope ends.
class SqliteSettings {
 public:
  SqliteSettings(const char* journal, const char* synchronous) {
    CPLSetThreadLocalConfigOption("OGR_SQLITE_JOURNAL", journal);
    CPLSetThreadLocalConfigOption("OGR_SQLITE_SYNCHRONOUS", synchronous);
  }
  ~SqliteSettings() {
    CPLSetThreadLocalConfigOption("OGR_SQLITE_JOURNAL", nullptr);
    CPLSetThreadLocalConfigOption("OGR_SQLITE_SYNCHRONOUS", nullptr);
  }
  SqliteSettings(const SqliteSettings&) = delete;
  SqliteSettings& operator=(const SqliteSettings&) = delete;
};

[[noreturn]] void FramesWriteFailed(const fs::path& path, const std::string& why) {
  throw OutputError("cannot write " + path.string() + ": " + why +
                    ". Fix: free disk space or check the folder's permissions; the published "
                    "store is unchanged");
}

}  // namespace

void CreateFramesGpkg(const fs::path& path, const std::string& crs_wkt, bool durable) {
  const fs::path temp = TemporaryPathFor(path);
  GdalErrorCapture capture;
  const OGRSpatialReference srs = SpatialReferenceOf(crs_wkt);
  OGRLayer* layer = nullptr;
  {
    // Private until renamed: no journal needed while it is built. The header then says WAL, so
    // the in-place updates of a running store never block, nor are blocked by, readers.
    const SqliteSettings settings("WAL", "OFF");
    GDALDriver* driver = GetGDALDriverManager()->GetDriverByName("GPKG");
    GDALDataset* dataset =
        driver ? driver->Create(temp.c_str(), 0, 0, 0, GDT_Unknown, nullptr) : nullptr;
    if (dataset != nullptr) {
      const char* layer_options[] = {"GEOMETRY_NAME=geom", "FID=fid", nullptr};
      layer = dataset->CreateLayer("frames", const_cast<OGRSpatialReference*>(&srs), wkbPolygon,
                                   const_cast<char**>(layer_options));
      if (layer != nullptr) {
        OGRFieldDefn index("frame_index", OFTInteger64);
        OGRFieldDefn time("time_s", OFTReal);
        OGRFieldDefn pos_only("pos_only", OFTInteger);
        pos_only.SetSubType(OFSTBoolean);
        OGRFieldDefn residual("residual_px", OFTReal);
        OGRFieldDefn inliers("inliers", OFTInteger);
        OGRFieldDefn status("status", OFTString);
        for (OGRFieldDefn* field : {&index, &time, &pos_only, &residual, &inliers, &status}) {
          layer->CreateField(field);
        }
      }
      GDALClose(dataset);
    }
  }
  if (layer == nullptr || capture.failed()) {
    std::error_code ignored;
    fs::remove(temp, ignored);
    FramesWriteFailed(path, capture.failed() ? capture.message()
                                             : std::string("GDAL cannot create the GeoPackage"));
  }
  RenameOrThrow(temp, path, durable);
}

namespace {

// One attempt at WriteFramesGpkg's transaction: "" once committed, else why not (rolled back).
std::string TryWriteFrames(const fs::path& path, const std::vector<FrameRecord>& changed,
                           bool durable) {
  GdalErrorCapture capture;
  bool written = false;
  {
    const SqliteSettings settings("WAL", durable ? "FULL" : "NORMAL");
    GDALDataset* dataset = GDALDataset::Open(path.c_str(), GDAL_OF_VECTOR | GDAL_OF_UPDATE);
    OGRLayer* layer = dataset ? dataset->GetLayerByName("frames") : nullptr;
    if (layer != nullptr && dataset->StartTransaction() == OGRERR_NONE) {
      written = true;
      for (const FrameRecord& record : changed) {
        OGRFeature* existing = layer->GetFeature(record.index + 1);
        OGRFeature feature(layer->GetLayerDefn());
        FillFeature(&feature, record, layer->GetSpatialRef());
        OGRErr status = OGRERR_NONE;
        if (existing != nullptr) {
          OGRFeature::DestroyFeature(existing);
          status = layer->SetFeature(&feature);
        } else {
          status = layer->CreateFeature(&feature);
        }
        if (status != OGRERR_NONE) {
          written = false;
          break;
        }
      }
      if (!written || capture.failed()) {
        dataset->RollbackTransaction();
        written = false;
      } else if (dataset->CommitTransaction() != OGRERR_NONE) {
        written = false;
      }
    }
    if (dataset != nullptr) GDALClose(dataset);
  }
  if (written && !capture.failed()) return "";
  return capture.failed() ? capture.message() : std::string("GDAL cannot update the GeoPackage");
}

std::atomic<int64_t> g_frames_gpkg_busy_retries{0};
std::atomic<int> g_closing_lock_budget_ms{kFramesGpkgClosingLockBudgetMs};

}  // namespace

int64_t FramesGpkgBusyRetries() { return g_frames_gpkg_busy_retries.load(); }
int FramesGpkgLiveLockBudgetMs() { return 250; }
int FramesGpkgClosingLockBudgetMs() { return g_closing_lock_budget_ms.load(); }
void SetFramesGpkgClosingLockBudgetMsForTesting(int ms) { g_closing_lock_budget_ms.store(ms); }

bool WriteFramesGpkg(const fs::path& path, const std::string& crs_wkt,
                     const std::vector<FrameRecord>& changed, bool durable, int locked_budget_ms) {
  if (!fs::exists(path)) CreateFramesGpkg(path, crs_wkt, durable);
  if (changed.empty()) return true;
  // In place, one SQLite transaction in write-ahead-log mode: a reader sees the records of the
  // last commit, never part of one, and a kill -9 mid-transaction leaves the last commit (SQLite
  // rolls the rest back when the file is next opened). The work is the changed rows and their
  // index pages, not a copy of a file that grows with the flight. "NORMAL" syncs at
  // checkpoints only (safe against a crash of this process; durable adds power loss).
  // Another connection can hold the file locked: a reader closing it last (SQLite then
  // checkpoints under an exclusive lock), or a program writing to it. GDAL's transaction starts
  // with a DROP TRIGGER after reading the schema, and SQLite answers such an upgrade from a read
  // to a write "database is locked" at once, without waiting in GDAL's 5 s busy timeout: under
  // load 3 runs in 60 of TileStoreTest.ConcurrentReaderProcessNeverSeesAnErrorOrATornTile
  // failed so (session 44), and a lock held for seconds failed every attempt at once
  // (session 45, TileStoreTest.AFramesGpkgLockedByAnotherProgramDefersItsRecordsNotThePublish).
  // The transaction commits whole or not at all, so it is tried again, 2..100 ms apart.
  std::string why;
  int waited_ms = 0;
  for (int attempt = 0;; ++attempt) {
    why = TryWriteFrames(path, changed, durable);
    if (why.empty()) return true;
    const bool busy = why.find("database is locked") != std::string::npos ||
                      why.find("database is busy") != std::string::npos;
    if (!busy) break;
    if (waited_ms >= locked_budget_ms) return false;
    const int pause_ms = std::min(100, 2 << std::min(attempt, 6));
    std::this_thread::sleep_for(std::chrono::milliseconds(pause_ms));
    waited_ms += pause_ms;
    g_frames_gpkg_busy_retries.fetch_add(1);
  }
  FramesWriteFailed(path, why);
}

void SettleFramesGpkg(const fs::path& path) {
  if (!fs::exists(path)) return;
  GdalErrorCapture capture;  // Best effort: a WAL-mode file is still a valid GeoPackage.
  const SqliteSettings settings("DELETE", "NORMAL");
  GDALDataset* dataset = GDALDataset::Open(path.c_str(), GDAL_OF_VECTOR | GDAL_OF_UPDATE);
  if (dataset != nullptr) GDALClose(dataset);
}

std::vector<FrameRecord> ReadFramesGpkg(const fs::path& path) {
  std::vector<FrameRecord> records;
  if (!fs::exists(path)) return records;
  GdalErrorCapture capture;
  GDALDataset* dataset = GDALDataset::Open(path.c_str(), GDAL_OF_VECTOR | GDAL_OF_READONLY);
  OGRLayer* layer = dataset ? dataset->GetLayerByName("frames") : nullptr;
  if (layer == nullptr) {
    if (dataset) GDALClose(dataset);
    throw InputError({path.string(), 0, 0, ""}, "not a frames GeoPackage",
                     "restore the file or start a new store (--overwrite)");
  }
  for (auto& feature : *layer) {
    FrameRecord record;
    record.index = feature->GetFieldAsInteger64("frame_index");
    record.time_s = feature->GetFieldAsDouble("time_s");
    record.pos_only = feature->GetFieldAsInteger("pos_only") != 0;
    record.residual_px = feature->GetFieldAsDouble("residual_px");
    record.inliers = feature->GetFieldAsInteger("inliers");
    record.status = feature->GetFieldAsString("status");
    const OGRGeometry* geometry = feature->GetGeometryRef();
    if (geometry && wkbFlatten(geometry->getGeometryType()) == wkbPolygon) {
      const OGRLinearRing* ring = geometry->toPolygon()->getExteriorRing();
      for (int c = 0; c < 4 && ring && c < ring->getNumPoints(); ++c) {
        record.footprint_m[c] = {ring->getX(c), ring->getY(c)};
      }
    }
    records.push_back(record);
  }
  GDALClose(dataset);
  return records;
}

std::string UtcNow() {
  const std::time_t now = std::chrono::system_clock::to_time_t(std::chrono::system_clock::now());
  std::tm utc{};
  gmtime_r(&now, &utc);
  char text[32];
  std::strftime(text, sizeof(text), "%Y-%m-%dT%H:%M:%SZ", &utc);
  return text;
}

}  // namespace irmosaic::store
