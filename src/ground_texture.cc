// The simulator's ground: a georeferenced raster on the truth's mosaic plane, extended and
// detailed by deterministic fractal value noise, generated in cached tiles (docs/simulator.md).
#include <gdal_priv.h>
#include <ogr_spatialref.h>

#include <algorithm>
#include <cmath>
#include <list>
#include <mutex>
#include <opencv2/imgproc.hpp>
#include <sstream>
#include <unordered_map>

#include "bilinear_warp.h"
#include "irmosaic/error.h"
#include "irmosaic/simulator.h"

namespace irmosaic {
namespace {

constexpr int kTile = 256;  // Tile side, mosaic pixels.
constexpr int kStep = SyntheticGround::kSampleStep;
constexpr int kTileSamples = kTile / kStep;  // Tile side in stored samples.
// Grid steps (mosaic px) a tile is synthesised on, coarse to fine; the last is the stored one.
constexpr int kLevels[] = {8, kStep};
constexpr double kSourceStd = 0.15;  // The raster is normalised to mean 0.5 and this std.
constexpr double kBackgroundStd = 0.15;

uint64_t SplitMix(uint64_t x) {
  x += 0x9E3779B97F4A7C15ull;
  x = (x ^ (x >> 30)) * 0xBF58476D1CE4E5B9ull;
  x = (x ^ (x >> 27)) * 0x94D049BB133111EBull;
  return x ^ (x >> 31);
}

// Uniform in [-1, 1) from a hash.
float HashUniform(uint64_t h) {
  return static_cast<float>(static_cast<double>(h >> 11) * (2.0 / 9007199254740992.0) - 1.0);
}

// One octave of value noise: a lattice of hashed values, rotated and offset so no two octaves
// share grid lines, interpolated bilinearly.
struct Octave {
  double spacing_px = 0.0;
  double amplitude = 0.0;
  Eigen::Matrix2d lattice_from_mosaic;  // Rotation / spacing.
  Eigen::Vector2d offset;
  uint64_t salt = 0;
  int level = 1;
};

// Coarsest level grid that still samples a feature of this size `per_feature` times.
int LevelFor(double feature_px, double per_feature) {
  for (int s : kLevels) {
    if (s <= feature_px / per_feature) return s;
  }
  return 1;
}

std::vector<Octave> MakeOctaves(uint64_t seed, uint64_t band, double min_spacing,
                                double max_spacing, double exponent, double total_std) {
  std::vector<Octave> octaves;
  double sum_sq = 0.0;
  for (double spacing = min_spacing; spacing <= max_spacing; spacing *= 2.0) {
    Octave o;
    o.spacing_px = spacing;
    o.salt = SplitMix(seed * 1000003ull + band * 7919ull + octaves.size());
    const double angle = M_PI * (HashUniform(SplitMix(o.salt + 1)) + 1.0);
    o.lattice_from_mosaic = Eigen::Rotation2Dd(angle).toRotationMatrix() / spacing;
    o.offset = {0.5 * (HashUniform(SplitMix(o.salt + 2)) + 1.0),
                0.5 * (HashUniform(SplitMix(o.salt + 3)) + 1.0)};
    o.amplitude = std::pow(spacing, exponent);
    o.level = LevelFor(spacing, 2.0);
    // Bilinear value noise of iid uniform[-1, 1] lattice values has mean variance (1/3)(4/9).
    sum_sq += o.amplitude * o.amplitude * (4.0 / 27.0);
    octaves.push_back(o);
  }
  const double norm = sum_sq > 0 ? total_std / std::sqrt(sum_sq) : 0.0;
  for (Octave& o : octaves) o.amplitude *= norm;
  return octaves;
}

// Adds one octave to a level grid whose sample (j, i) is mosaic pixel origin + step * (j, i).
void AddOctave(const Octave& o, double origin_col, double origin_row, double step, cv::Mat* grid) {
  const Eigen::Vector2d q0 =
      o.lattice_from_mosaic * Eigen::Vector2d(origin_col, origin_row) + o.offset;
  const Eigen::Matrix2d a = o.lattice_from_mosaic * step;
  const double nj = grid->cols - 1, ni = grid->rows - 1;
  Eigen::Vector2d lo = q0, hi = q0;
  for (const Eigen::Vector2d& c :
       {Eigen::Vector2d(nj, 0), Eigen::Vector2d(0, ni), Eigen::Vector2d(nj, ni)}) {
    const Eigen::Vector2d q = q0 + a * c;
    lo = lo.cwiseMin(q);
    hi = hi.cwiseMax(q);
  }
  const int64_t ix0 = static_cast<int64_t>(std::floor(lo.x())) - 1;
  const int64_t iy0 = static_cast<int64_t>(std::floor(lo.y())) - 1;
  const int bw = static_cast<int>(std::floor(hi.x()) - ix0) + 3;
  const int bh = static_cast<int>(std::floor(hi.y()) - iy0) + 3;
  cv::Mat lattice(bh, bw, CV_32F);
  for (int y = 0; y < bh; ++y) {
    float* row = lattice.ptr<float>(y);
    const uint64_t hy = static_cast<uint64_t>(iy0 + y) * 0xD6E8FEB86659FD93ull;
    for (int x = 0; x < bw; ++x) {
      row[x] = HashUniform(
          SplitMix(o.salt ^ hy ^ (static_cast<uint64_t>(ix0 + x) * 0x9E3779B97F4A7C15ull)));
    }
  }
  const cv::Matx33d m(a(0, 0), a(0, 1), q0.x() - static_cast<double>(ix0), a(1, 0), a(1, 1),
                      q0.y() - static_cast<double>(iy0), 0.0, 0.0, 1.0);
  sim::AddWarpBilinear(lattice, m, static_cast<float>(o.amplitude), grid);
}

struct TileKey {
  int64_t col, row;
  bool operator==(const TileKey& o) const { return col == o.col && row == o.row; }
};
struct TileKeyHash {
  size_t operator()(const TileKey& k) const {
    return static_cast<size_t>(
        SplitMix(static_cast<uint64_t>(k.col) * 31 + static_cast<uint64_t>(k.row)));
  }
};

struct OgrTransformDeleter {
  void operator()(OGRCoordinateTransformation* t) const {
    OGRCoordinateTransformation::DestroyCT(t);
  }
};
using OgrTransform = std::unique_ptr<OGRCoordinateTransformation, OgrTransformDeleter>;

}  // namespace

struct SyntheticGround::Impl {
  SynthOptions options;
  // The raster (empty without one), normalised gray and its blending weight (0 outside data).
  cv::Mat source, weight;
  double gt[6] = {0, 1, 0, 0, 0, -1};
  double source_px_m = 1.0;  // Native pixel size (metres on the ground).
  double plane_scale = 1.0;  // Plane metres -> raster metres (ground_m_per_source_px).
  bool earth_crs = false;    // Raster CRS convertible from the tangent plane through PROJ.
  OGRSpatialReference source_srs;
  OgrTransform plane_to_source;  // Tangent plane (ortho) -> raster CRS.
  double lat0 = 0.0, lon0 = 0.0;
  MosaicGrid grid;
  int source_level = 8;
  std::vector<Octave> background, detail;
  double pixel_texture_std = 0.0;

  mutable std::mutex mutex;
  mutable std::list<std::pair<TileKey, cv::Mat>> lru;
  mutable std::unordered_map<TileKey, std::list<std::pair<TileKey, cv::Mat>>::iterator, TileKeyHash>
      tiles;
  mutable int64_t generated = 0;
  size_t max_tiles = 512;

  void LoadRaster(const std::string& path);
  Eigen::Vector2d SourcePixelFromMosaic(double col, double row) const;
  cv::Mat Generate(int64_t tile_col, int64_t tile_row) const;
  const cv::Mat& Tile(int64_t tile_col, int64_t tile_row) const;
};

void SyntheticGround::Impl::LoadRaster(const std::string& path) {
  GDALAllRegister();
  const SourceLocation where{path, 0, 0, "ground_path"};
  std::unique_ptr<GDALDataset> ds(
      GDALDataset::Open(path.c_str(), GDAL_OF_RASTER | GDAL_OF_READONLY));
  if (!ds) throw InputError(where, "GDAL cannot open the ground raster", "give a readable GeoTIFF");
  if (ds->GetGeoTransform(gt) != CE_None || ds->GetSpatialRef() == nullptr) {
    throw InputError(where, "the ground raster has no georeference (geotransform and CRS)",
                     "give a georeferenced GeoTIFF");
  }
  const int w = ds->GetRasterXSize(), h = ds->GetRasterYSize();
  if (w < 16 || h < 16) throw InputError(where, "the ground raster is tiny", "give >= 16x16 px");
  cv::Mat gray(h, w, CV_32F, cv::Scalar(0)), valid(h, w, CV_8U, cv::Scalar(255));
  const int bands = ds->GetRasterCount();
  std::vector<int> colour;
  // A pixel is nodata only when every band used is at its nodata value: one dark band (water
  // in the near infrared) is data.
  cv::Mat nodata_bands(h, w, CV_8U, cv::Scalar(0));
  int bands_with_nodata = 0;
  for (int b = 1; b <= bands; ++b) {
    GDALRasterBand* band = ds->GetRasterBand(b);
    cv::Mat data(h, w, CV_32F);
    if (band->RasterIO(GF_Read, 0, 0, w, h, data.data, w, h, GDT_Float32, 0, 0) != CE_None) {
      throw InputError(where, "cannot read band " + std::to_string(b), "check the file");
    }
    if (band->GetColorInterpretation() == GCI_AlphaBand) {
      valid.setTo(0, data <= 0);
      continue;
    }
    if (colour.size() >= 3) continue;
    colour.push_back(b);
    gray += data;
    int has_nodata = 0;
    const double nodata = band->GetNoDataValue(&has_nodata);
    if (has_nodata) {
      ++bands_with_nodata;
      cv::Mat at_nodata = data == nodata;
      nodata_bands += at_nodata / 255;
    }
  }
  if (bands_with_nodata > 0 && bands_with_nodata == static_cast<int>(colour.size())) {
    valid.setTo(0, nodata_bands == bands_with_nodata);
  }
  if (colour.empty())
    throw InputError(where, "the raster has no data band", "give a gray/RGB raster");
  gray /= static_cast<double>(colour.size());
  cv::Scalar mean, stddev;
  cv::meanStdDev(gray, mean, stddev, valid);
  if (cv::countNonZero(valid) < 256 || stddev[0] <= 0) {
    throw InputError(where, "the raster has almost no valid, textured pixels", "give another one");
  }
  source = (gray - mean[0]) * (kSourceStd / stddev[0]) + 0.5;
  source.setTo(0.5, valid == 0);
  // Feather the data's edge so the raster fades into the fractal terrain without a seam.
  cv::Mat padded;
  cv::copyMakeBorder(valid, padded, 1, 1, 1, 1, cv::BORDER_CONSTANT, 0);
  cv::Mat dist;
  cv::distanceTransform(padded, dist, cv::DIST_L2, 3);
  const double feather = std::clamp(std::min(w, h) / 20.0, 4.0, 32.0);
  weight = dist(cv::Rect(1, 1, w, h)) / feather;
  cv::min(weight, 1.0, weight);

  source_srs = *ds->GetSpatialRef();
  source_srs.SetAxisMappingStrategy(OAMS_TRADITIONAL_GIS_ORDER);
  source_px_m = std::sqrt(std::abs(gt[1] * gt[5] - gt[2] * gt[4]));
  OGRErr err = OGRERR_NONE;
  const double semi_major = source_srs.GetSemiMajor(&err);
  earth_crs = err == OGRERR_NONE && std::abs(semi_major - 6378137.0) < 5000.0 &&
              (source_srs.IsProjected() || source_srs.IsGeographic());
  if (source_srs.IsGeographic()) source_px_m *= 111320.0;  // Degrees: nominal size only.
  if (earth_crs && !std::isfinite(options.origin_lat_deg)) {
    OGRSpatialReference wgs84;
    wgs84.SetWellKnownGeogCS("WGS84");
    wgs84.SetAxisMappingStrategy(OAMS_TRADITIONAL_GIS_ORDER);
    OgrTransform to_wgs84(OGRCreateCoordinateTransformation(&source_srs, &wgs84));
    double x = gt[0] + gt[1] * w / 2.0 + gt[2] * h / 2.0;
    double y = gt[3] + gt[4] * w / 2.0 + gt[5] * h / 2.0;
    if (!to_wgs84 || !to_wgs84->Transform(1, &x, &y)) {
      throw InputError(where, "the raster's centre cannot be converted to WGS84",
                       "give origin_lat_deg and origin_lon_deg");
    }
    lon0 = x;
    lat0 = y;
  } else if (!std::isfinite(options.origin_lat_deg)) {
    throw InputError(where, "the raster's CRS is not an Earth CRS, so it implies no origin",
                     "give origin_lat_deg and origin_lon_deg (it is then laid north-up)");
  }
}

SyntheticGround::SyntheticGround(const SynthOptions& options) : impl_(std::make_unique<Impl>()) {
  Impl& g = *impl_;
  g.options = options;
  g.lat0 = std::isfinite(options.origin_lat_deg) ? options.origin_lat_deg : 0.0;
  g.lon0 = std::isfinite(options.origin_lon_deg) ? options.origin_lon_deg : 0.0;
  if (!options.ground_path.empty()) g.LoadRaster(options.ground_path);
  if (std::isfinite(options.origin_lat_deg)) {
    g.lat0 = options.origin_lat_deg;
    g.lon0 = options.origin_lon_deg;
  }
  g.max_tiles = std::max<size_t>(
      16, options.ground_cache_mb * 1024 * 1024 / (kTileSamples * kTileSamples * 4));
}

SyntheticGround::~SyntheticGround() = default;
double SyntheticGround::origin_lat_deg() const { return impl_->lat0; }
double SyntheticGround::origin_lon_deg() const { return impl_->lon0; }

int64_t SyntheticGround::tiles_generated() const {
  std::lock_guard<std::mutex> lock(impl_->mutex);
  return impl_->generated;
}

int64_t SyntheticGround::cached_bytes() const {
  std::lock_guard<std::mutex> lock(impl_->mutex);
  int64_t bytes = 0;
  for (const auto& [key, tile] : impl_->lru) {
    bytes += static_cast<int64_t>(tile.total() * tile.elemSize());
  }
  return bytes;
}

void SyntheticGround::Attach(const LocalFrame& frame, const MosaicGrid& grid) {
  Impl& g = *impl_;
  g.grid = grid;
  const uint64_t seed = g.options.seed;
  // Background terrain: features 32 px to 4096 px; detail: 4 px to 16 px plus per-pixel
  // texture at the finest scale (docs/simulator.md). A share 1/4 of the detail variance goes to
  // the per-pixel texture.
  g.background = MakeOctaves(seed, 1, 32.0, 4096.0, 0.8, kBackgroundStd);
  g.detail = MakeOctaves(seed, 2, 4.0, 16.0, 0.3, g.options.detail_contrast * std::sqrt(0.75));
  g.pixel_texture_std = g.options.detail_contrast * 0.5;
  for (Octave& o : g.background) o.level = 8;
  if (g.source.empty()) return;
  const double ground_px_m =
      g.options.ground_m_per_source_px > 0 ? g.options.ground_m_per_source_px : g.source_px_m;
  g.plane_scale = g.source_px_m / ground_px_m;
  // Two samples per raster pixel suffice on the coarse grid: the raster is bicubic there and
  // the fine grid interpolates between its samples.
  g.source_level = LevelFor(ground_px_m / grid.gsd_m, 2.0);
  if (g.earth_crs) {
    OGRSpatialReference plane_srs;
    plane_srs.importFromWkt(frame.CrsWkt().c_str());
    plane_srs.SetAxisMappingStrategy(OAMS_TRADITIONAL_GIS_ORDER);
    g.plane_to_source.reset(OGRCreateCoordinateTransformation(&plane_srs, &g.source_srs));
    if (!g.plane_to_source) {
      throw InputError({g.options.ground_path, 0, 0, "ground_path"},
                       "PROJ cannot convert the tangent plane to the raster's CRS",
                       "give a raster in a common Earth CRS");
    }
  }
}

Eigen::Vector2d SyntheticGround::Impl::SourcePixelFromMosaic(double col, double row) const {
  const Eigen::Vector2d plane = grid.PlaneFromPixel({col, row}) * plane_scale;
  double x = plane.x(), y = plane.y();
  if (plane_to_source) {
    if (!plane_to_source->Transform(1, &x, &y)) return {-1e9, -1e9};
  } else {
    // Laid north-up: the raster's centre at the origin, its axes east and north.
    x += gt[0] + gt[1] * source.cols / 2.0 + gt[2] * source.rows / 2.0;
    y += gt[3] + gt[4] * source.cols / 2.0 + gt[5] * source.rows / 2.0;
  }
  // Inverse geotransform; pixel centres at integers (OpenCV), GDAL's edges at integers.
  const double dx = x - gt[0], dy = y - gt[3];
  const double det = gt[1] * gt[5] - gt[2] * gt[4];
  const double u = (gt[5] * dx - gt[2] * dy) / det, v = (-gt[4] * dx + gt[1] * dy) / det;
  return {u - 0.5, v - 0.5};
}

cv::Mat SyntheticGround::Impl::Generate(int64_t tile_col, int64_t tile_row) const {
  const int64_t c0 = tile_col * kTile, r0 = tile_row * kTile;
  cv::Mat acc;
  int prev_step = 0;
  for (int step : kLevels) {
    // Level grid with one sample of margin: sample (j, i) is the centre of the step x step
    // block of mosaic pixels starting at (c0 + step (j - 1), r0 + step (i - 1)), i.e. at mosaic
    // pixel coordinate c0 + step (j - 1) + (step - 1) / 2. cv::resize uses the same block-centre
    // convention, so a coarse level is upsampled with one resize and a crop.
    const int n = kTile / step + 2;
    const double oc = static_cast<double>(c0) - step + (step - 1) / 2.0;
    const double orow = static_cast<double>(r0) - step + (step - 1) / 2.0;
    cv::Mat cur;
    if (acc.empty()) {
      cur = cv::Mat(n, n, CV_32F, cv::Scalar(0.5));
    } else {
      const int k = prev_step / step;
      cv::Mat up;
      cv::resize(acc, up, cv::Size(acc.cols * k, acc.rows * k), 0, 0, cv::INTER_LINEAR);
      cur = up(cv::Rect(k - 1, k - 1, n, n)).clone();
    }
    for (const Octave& o : background) {
      if (o.level == step) AddOctave(o, oc, orow, step, &cur);
    }
    if (!source.empty() && step == source_level) {
      // A tile spans ~100 m: an affine through three exact points is exact to far below a px.
      const cv::Point2f dst_pts[3] = {
          {0, 0}, {static_cast<float>(n - 1), 0}, {0, static_cast<float>(n - 1)}};
      cv::Point2f src_pts[3];
      for (int p = 0; p < 3; ++p) {
        const Eigen::Vector2d sp =
            SourcePixelFromMosaic(oc + step * dst_pts[p].x, orow + step * dst_pts[p].y);
        src_pts[p] = cv::Point2f(static_cast<float>(sp.x()), static_cast<float>(sp.y()));
      }
      const cv::Mat m = cv::getAffineTransform(dst_pts, src_pts);
      cv::Mat value, w;
      cv::warpAffine(source, value, m, cur.size(), cv::INTER_CUBIC | cv::WARP_INVERSE_MAP,
                     cv::BORDER_REPLICATE);
      cv::warpAffine(weight, w, m, cur.size(), cv::INTER_LINEAR | cv::WARP_INVERSE_MAP,
                     cv::BORDER_CONSTANT, cv::Scalar(0));
      // cur = w * value + (1 - w) * cur
      cv::Mat diff = value - cur;
      cur += diff.mul(w);
    }
    for (const Octave& o : detail) {
      if (o.level == step) AddOctave(o, oc, orow, step, &cur);
    }
    if (step == kStep && pixel_texture_std > 0) {
      // Finest texture: independent per stored sample, hashed from its global index.
      const uint64_t salt = SplitMix(options.seed * 0x2545F4914F6CDD1Dull + 77);
      const float amp = static_cast<float>(pixel_texture_std * std::sqrt(3.0));
      for (int i = 0; i < n; ++i) {
        float* row = cur.ptr<float>(i);
        const uint64_t hy = static_cast<uint64_t>(r0 / kStep + i - 1) * 0xD6E8FEB86659FD93ull;
        for (int j = 0; j < n; ++j) {
          row[j] += amp * HashUniform(SplitMix(
                              salt ^ hy ^
                              (static_cast<uint64_t>(c0 / kStep + j - 1) * 0x9E3779B97F4A7C15ull)));
        }
      }
    }
    acc = cur;
    prev_step = step;
  }
  return acc(cv::Rect(1, 1, kTileSamples, kTileSamples)).clone();
}

const cv::Mat& SyntheticGround::Impl::Tile(int64_t tile_col, int64_t tile_row) const {
  const TileKey key{tile_col, tile_row};
  auto it = tiles.find(key);
  if (it != tiles.end()) {
    lru.splice(lru.begin(), lru, it->second);
    return it->second->second;
  }
  lru.emplace_front(key, Generate(tile_col, tile_row));
  ++generated;
  tiles[key] = lru.begin();
  while (lru.size() > max_tiles) {
    tiles.erase(lru.back().first);
    lru.pop_back();
  }
  return lru.front().second;
}

void SyntheticGround::Fill(int64_t col0, int64_t row0, int cols, int rows, cv::Mat* out) const {
  out->create(rows, cols, CV_32F);
  constexpr int64_t n = kTileSamples;
  auto floor_div = [](int64_t a) { return a >= 0 ? a / n : -((-a + n - 1) / n); };
  std::lock_guard<std::mutex> lock(impl_->mutex);
  for (int64_t tr = floor_div(row0); tr * n < row0 + rows; ++tr) {
    for (int64_t tc = floor_div(col0); tc * n < col0 + cols; ++tc) {
      const cv::Mat& tile = impl_->Tile(tc, tr);
      const int64_t x0 = std::max(col0, tc * n), x1 = std::min(col0 + cols, (tc + 1) * n);
      const int64_t y0 = std::max(row0, tr * n), y1 = std::min(row0 + rows, (tr + 1) * n);
      const cv::Rect from(static_cast<int>(x0 - tc * n), static_cast<int>(y0 - tr * n),
                          static_cast<int>(x1 - x0), static_cast<int>(y1 - y0));
      const cv::Rect to(static_cast<int>(x0 - col0), static_cast<int>(y0 - row0), from.width,
                        from.height);
      tile(from).copyTo((*out)(to));
    }
  }
}

}  // namespace irmosaic
