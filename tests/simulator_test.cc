#include "irmosaic/simulator.h"

#include <gdal_priv.h>
#include <gtest/gtest.h>
#include <ogr_spatialref.h>

#include <cmath>
#include <filesystem>
#include <opencv2/imgproc.hpp>

#include "irmosaic/error.h"
#include "test_data.h"

namespace irmosaic {
namespace {

namespace fs = std::filesystem;

// A 1 m UTM raster of Gaussian blobs on a flat background, at known UTM positions.
struct BlobRaster {
  std::string path;
  double x0 = 460000.0, y0 = 5230000.0;  // Top-left corner, UTM 32N metres.
  int size = 1200;
  double spacing_m = 40.0, sigma_m = 1.2;

  Eigen::Vector2d BlobUtm(int i, int j) const {
    return {x0 + spacing_m * (i + 0.5), y0 - spacing_m * (j + 0.5)};
  }
  int count() const { return static_cast<int>(size / spacing_m); }

  void Write() {
    path = (fs::temp_directory_path() / ("irmosaic_blobs_" + std::to_string(::getpid()) + ".tif"))
               .string();
    cv::Mat img(size, size, CV_32F, cv::Scalar(50.0f));
    for (int j = 0; j < count(); ++j) {
      for (int i = 0; i < count(); ++i) {
        const Eigen::Vector2d c = BlobUtm(i, j);
        // Pixel (col, row) centre is at UTM (x0 + col + 0.5, y0 - row - 0.5).
        const double cc = c.x() - x0 - 0.5, cr = y0 - c.y() - 0.5;
        for (int r = static_cast<int>(cr) - 8; r <= static_cast<int>(cr) + 8; ++r) {
          for (int q = static_cast<int>(cc) - 8; q <= static_cast<int>(cc) + 8; ++q) {
            const double d2 = (q - cc) * (q - cc) + (r - cr) * (r - cr);
            img.at<float>(r, q) +=
                static_cast<float>(150.0 * std::exp(-0.5 * d2 / (sigma_m * sigma_m)));
          }
        }
      }
    }
    GDALAllRegister();
    GDALDriver* driver = GetGDALDriverManager()->GetDriverByName("GTiff");
    GDALDataset* ds = driver->Create(path.c_str(), size, size, 1, GDT_Float32, nullptr);
    double gt[6] = {x0, 1.0, 0.0, y0, 0.0, -1.0};
    ds->SetGeoTransform(gt);
    OGRSpatialReference srs;
    srs.importFromEPSG(32632);
    ds->SetSpatialRef(&srs);
    ASSERT_EQ(ds->GetRasterBand(1)->RasterIO(GF_Write, 0, 0, size, size, img.data, size, size,
                                             GDT_Float32, 0, 0),
              CE_None);
    GDALClose(ds);
  }
  ~BlobRaster() {
    if (!path.empty()) fs::remove(path);
  }
};

SynthOptions QuietOptions() {
  SynthOptions o;
  o.sensor.noise = false;
  o.sensor.column_noise = false;
  o.sensor.dead_pixels = false;
  o.sensor.vignetting = false;
  o.sensor.gain_drift = false;
  return o;
}

SynthOptions ProceduralOptions() {
  SynthOptions o;
  o.origin_lat_deg = 47.2;
  o.origin_lon_deg = 8.5;
  return o;
}

// A ground point rendered in a frame, found there and mapped through the true homography,
// lands on the mosaic pixel where the point truly is (through independent geodesy: the blob's
// UTM position -> WGS84 by PROJ -> the truth's plane).
void CheckTruthAgreesWithRenderedPixels(const CameraModel& camera, int frame_step,
                                        const std::string& label) {
  BlobRaster raster;
  raster.Write();
  SynthOptions o = QuietOptions();
  o.camera = camera;
  o.ground_path = raster.path;
  o.detail_contrast = 0.0;
  o.altitude_m = 300.0;
  o.frame_count = 40;
  o.heading_deg = 25.0;
  // Motion blur and the optics PSF stay on: they are symmetric and must not move the truth.
  FlightSimulator sim(o);

  OGRSpatialReference utm, wgs84;
  utm.importFromEPSG(32632);
  wgs84.SetWellKnownGeogCS("WGS84");
  utm.SetAxisMappingStrategy(OAMS_TRADITIONAL_GIS_ORDER);
  wgs84.SetAxisMappingStrategy(OAMS_TRADITIONAL_GIS_ORDER);
  std::unique_ptr<OGRCoordinateTransformation> to_wgs84(
      OGRCreateCoordinateTransformation(&utm, &wgs84));
  std::vector<Eigen::Vector2d> blobs_mosaic;
  for (int j = 0; j < raster.count(); ++j) {
    for (int i = 0; i < raster.count(); ++i) {
      Eigen::Vector2d p = raster.BlobUtm(i, j);
      double x = p.x(), y = p.y();
      ASSERT_TRUE(to_wgs84->Transform(1, &x, &y));  // NOLINT: gtest ASSERT in a void helper.
      blobs_mosaic.push_back(sim.grid().PixelFromPlane(sim.frame().PlaneFromGeodetic(y, x)));
    }
  }

  double worst = 0.0, sum_sq = 0.0;
  int checked = 0;
  for (int index = 0; index < o.frame_count; index += frame_step) {
    const SimFrame f = sim.Render(index);
    cv::Mat img;
    f.image.convertTo(img, CV_64F);
    const Eigen::Matrix3d image_from_mosaic = f.true_mosaic_from_image.inverse();
    for (const Eigen::Vector2d& m : blobs_mosaic) {
      // Where the blob is recorded: the truth maps undistorted pixels; the lens distorts them.
      const Eigen::Vector2d undistorted = ApplyHomography(image_from_mosaic, m);
      if (undistorted.x() < 0 || undistorted.y() < 0 || undistorted.x() > img.cols ||
          undistorted.y() > img.rows) {
        continue;
      }
      const Eigen::Vector2d guess = camera.Distort(undistorted);
      const int r = 40;  // About 4 sigma of a blob: the window holds all of it.
      if (guess.x() < r + 2 || guess.y() < r + 2 || guess.x() > img.cols - r - 3 ||
          guess.y() > img.rows - r - 3) {
        continue;
      }
      const cv::Rect win(static_cast<int>(std::lround(guess.x())) - r,
                         static_cast<int>(std::lround(guess.y())) - r, 2 * r + 1, 2 * r + 1);
      const cv::Mat patch = img(win);
      // Background: the median of the window's border (the blob's tails are far below it).
      std::vector<double> border;
      for (int k = 0; k < patch.rows; ++k) {
        border.insert(border.end(), {patch.at<double>(0, k), patch.at<double>(patch.rows - 1, k),
                                     patch.at<double>(k, 0), patch.at<double>(k, patch.cols - 1)});
      }
      std::nth_element(border.begin(), border.begin() + border.size() / 2, border.end());
      const double lo = border[border.size() / 2];
      // Centroid of the blob on the ground: each recorded pixel placed by the truth (undistort,
      // then the true homography) and weighted by the ground area it covers (|det J|, by
      // central differences), so the perspective does not bias the estimate the way an
      // image-space centroid would.
      const Eigen::Matrix3d& h = f.true_mosaic_from_image;
      auto place = [&](double px, double py) {
        return ApplyHomography(h, camera.Undistort({px, py}));
      };
      double sw = 0;
      Eigen::Vector2d sum = Eigen::Vector2d::Zero();
      for (int y = 0; y < patch.rows; ++y) {
        for (int x = 0; x < patch.cols; ++x) {
          const double px = win.x + x, py = win.y + y;
          Eigen::Matrix2d jac;
          jac.col(0) = place(px + 0.5, py) - place(px - 0.5, py);
          jac.col(1) = place(px, py + 0.5) - place(px, py - 0.5);
          const double w = std::max(0.0, patch.at<double>(y, x) - lo) * std::abs(jac.determinant());
          sw += w;
          sum += w * place(px, py);
        }
      }
      const Eigen::Vector2d ev = sum / sw - m;
      const double e = ev.norm();
      worst = std::max(worst, e);
      sum_sq += e * e;
      ++checked;
    }
  }
  ASSERT_GE(checked, 20);
  EXPECT_LT(worst, 0.1) << "mosaic pixels, over " << checked << " blobs";
  std::cout << "truth consistency (" << label << "): " << checked << " blobs, rms "
            << std::sqrt(sum_sq / checked) << " px, max " << worst << " px\n";
}

TEST(Simulator, TruthAgreesWithRenderedPixels) {
  CheckTruthAgreesWithRenderedPixels(DefaultInfraredCamera(), 3, "pinhole");
}

// With lens distortion the frame is rendered through undistort + homography; the truth (the
// homography of undistorted pixels) still holds. k1 = -0.3 moves the corners by ~3.5 px.
TEST(Simulator, TruthAgreesWithRenderedPixelsThroughLensDistortion) {
  CameraModel camera = DefaultInfraredCamera();
  camera.distortion = {-0.3, 0.0, 0.0, 0.0};
  CheckTruthAgreesWithRenderedPixels(camera, 7, "distortion k1 = -0.3");
}

TEST(Simulator, TruthHomographyMatchesExactRays) {
  FlightSimulator sim(ProceduralOptions());
  EXPECT_LT(sim.summary().truth_fit_max_px, 0.05);
}

TEST(Simulator, DefaultOverlapsMeetTargets) {
  FlightSimulator sim(ProceduralOptions());
  const FlightSummary& s = sim.summary();
  EXPECT_NEAR(s.along_sweep_overlap, 0.25, 0.04);
  EXPECT_NEAR(s.between_sweep_overlap_min, 0.15, 0.03);
  EXPECT_GT(s.between_sweep_overlap, 0.15);
  EXPECT_LT(s.between_sweep_overlap, 0.35);
}

TEST(Simulator, PosErrorsMatchConfiguredSigmas) {
  SynthOptions o = ProceduralOptions();
  o.frame_count = 1000;
  o.position_sigma_m = 2.0;
  o.position_bias_m = {1.0, -3.0, 0.5};
  o.attitude_sigma_deg = 0.3;
  o.attitude_bias_deg = {0.2, -0.1, 0.0};
  o.time_offset_s = 0.013;
  FlightSimulator sim(o);
  const int n = o.frame_count;
  std::array<std::vector<double>, 6> err;
  for (int i = 0; i < n; ++i) {
    const PosRecord t = sim.TruePos(i), m = sim.MeasuredPosRecord(i);
    ASSERT_NEAR(m.time_s - t.time_s, 0.013, 1e-12);
    const Eigen::Vector3d et = sim.frame().EnuFromGeodetic(t.lat_deg, t.lon_deg, 0.0);
    const Eigen::Vector3d em = sim.frame().EnuFromGeodetic(m.lat_deg, m.lon_deg, 0.0);
    err[0].push_back(em.x() - et.x());
    err[1].push_back(em.y() - et.y());
    err[2].push_back(m.height_m - t.height_m);
    err[3].push_back(m.roll_deg - t.roll_deg);
    err[4].push_back(m.pitch_deg - t.pitch_deg);
    err[5].push_back(m.yaw_deg - t.yaw_deg);
  }
  const double sigma[6] = {2.0, 2.0, 2.0, 0.3, 0.3, 0.3};
  const double bias[6] = {1.0, -3.0, 0.5, 0.2, -0.1, 0.0};
  for (int a = 0; a < 6; ++a) {
    double mean = 0, var = 0;
    for (double e : err[a]) mean += e;
    mean /= n;
    for (double e : err[a]) var += (e - mean) * (e - mean);
    const double sd = std::sqrt(var / (n - 1));
    EXPECT_NEAR(sd, sigma[a], 0.1 * sigma[a]) << "axis " << a;
    EXPECT_NEAR(mean, bias[a], 4.0 * sigma[a] / std::sqrt(n)) << "axis " << a;
  }
  // The POS log the pipeline gets carries the same records.
  const PosTrack track = sim.MeasuredPos();
  ASSERT_EQ(track.records().size(), static_cast<size_t>(n));
  EXPECT_DOUBLE_EQ(track.records()[17].lat_deg, sim.MeasuredPosRecord(17).lat_deg);
}

double MeasuredPsnr(int bit_depth, double target_db) {
  SynthOptions clean = QuietOptions();
  clean.origin_lat_deg = 47.2;
  clean.origin_lon_deg = 8.5;
  clean.frame_count = 30;
  clean.sensor.bit_depth = bit_depth;
  SynthOptions noisy = clean;
  noisy.sensor.noise = true;
  noisy.sensor.noise_psnr_db = target_db;
  FlightSimulator a(clean), b(noisy);
  double sum_sq = 0;
  double count = 0;
  for (int i = 0; i < clean.frame_count; i += 6) {
    cv::Mat x, y;
    a.Render(i).image.convertTo(x, CV_64F);
    b.Render(i).image.convertTo(y, CV_64F);
    cv::Mat d = x - y;
    sum_sq += d.dot(d);
    count += static_cast<double>(d.total());
  }
  const double peak = bit_depth == 8 ? 255.0 : 65535.0;
  return 10.0 * std::log10(peak * peak / (sum_sq / count));
}

TEST(Simulator, NoiseMeetsTargetPsnr) {
  for (double target : {20.0, 30.0, 40.0}) {
    EXPECT_NEAR(MeasuredPsnr(16, target), target, 0.5) << "16-bit, target " << target;
  }
  EXPECT_NEAR(MeasuredPsnr(8, 30.0), 30.0, 0.5) << "8-bit";
}

TEST(Simulator, DeterministicInAnyOrder) {
  SynthOptions o = ProceduralOptions();
  o.frame_count = 20;
  FlightSimulator a(o), b(o);
  const cv::Mat late = a.Render(15).image;
  const cv::Mat first_a = a.Render(3).image;
  const cv::Mat first_b = b.Render(3).image;
  EXPECT_EQ(cv::norm(first_a, first_b, cv::NORM_INF), 0.0);
  EXPECT_EQ(cv::norm(late, b.Render(15).image, cv::NORM_INF), 0.0);
  EXPECT_EQ(first_a.type(), CV_16UC1);
  o.seed = 2;
  FlightSimulator c(o);
  EXPECT_GT(cv::norm(first_a, c.Render(3).image, cv::NORM_L1), 0.0);
}

TEST(Simulator, GroundIsNotRepeated) {
  // Texture far apart must not correlate (no tiling, no mirroring): a patch and the same-sized
  // patches one and two tiles away (128 samples: 256 mosaic px) differ.
  SynthOptions o = ProceduralOptions();
  FlightSimulator sim(o);
  cv::Mat a, b, c;
  sim.ground().Fill(0, 0, 200, 200, &a);
  sim.ground().Fill(128, 0, 200, 200, &b);
  sim.ground().Fill(0, 256, 200, 200, &c);
  cv::Mat r;
  cv::matchTemplate(a, b, r, cv::TM_CCOEFF_NORMED);
  EXPECT_LT(r.at<float>(0, 0), 0.5);
  cv::matchTemplate(a, c, r, cv::TM_CCOEFF_NORMED);
  EXPECT_LT(r.at<float>(0, 0), 0.5);
  // Seamless: a region read across a tile border equals the same region read in two halves.
  cv::Mat whole, left, right;
  sim.ground().Fill(72, 10, 112, 50, &whole);
  sim.ground().Fill(72, 10, 56, 50, &left);
  sim.ground().Fill(128, 10, 56, 50, &right);
  EXPECT_EQ(cv::norm(whole(cv::Rect(0, 0, 56, 50)), left, cv::NORM_INF), 0.0);
  EXPECT_EQ(cv::norm(whole(cv::Rect(56, 0, 56, 50)), right, cv::NORM_INF), 0.0);
  // And smooth across the border: the jump there is like any other neighbour difference.
  cv::Mat dx = cv::abs(whole(cv::Rect(1, 0, 111, 50)) - whole(cv::Rect(0, 0, 111, 50)));
  const double border_jump = cv::mean(dx.col(55))[0], typical = cv::mean(dx)[0];
  EXPECT_LT(border_jump, 2.0 * typical);
}

TEST(Simulator, WideSweepIsAccepted) {
  SynthOptions o = ProceduralOptions();
  o.frames_per_sweep = 10;  // +-49 degrees: widest ray 60 degrees off nadir.
  std::string why;
  EXPECT_TRUE(o.IsValid(&why)) << why;
  FlightSimulator sim(o);
  EXPECT_NEAR(sim.summary().along_sweep_overlap, 0.25, 0.04);
  EXPECT_NEAR(sim.summary().between_sweep_overlap_min, 0.15, 0.03);
}

TEST(Simulator, OptionsJsonRoundTripAndErrors) {
  SynthOptions o = ProceduralOptions();
  o.frame_count = 123;
  o.sensor.bit_depth = 8;
  o.position_bias_m = {1, 2, 3};
  const SynthOptions back = SynthOptions::FromJson(o.ToJson(), "test");
  EXPECT_EQ(back.frame_count, 123);
  EXPECT_EQ(back.sensor.bit_depth, 8);
  EXPECT_EQ(back.position_bias_m, o.position_bias_m);
  EXPECT_DOUBLE_EQ(back.origin_lat_deg, 47.2);
  EXPECT_THROW(SynthOptions::FromJson(R"({"altitud_m": 100})", "test"), InputError);
  EXPECT_THROW(SynthOptions::FromJson(R"({"sensor": {"bit_depth": 12}, "origin_lat_deg": 1,
                                          "origin_lon_deg": 2})",
                                      "test"),
               InputError);
  SynthOptions bad = ProceduralOptions();
  bad.frames_per_sweep = 14;  // Looks past 75 degrees off nadir.
  EXPECT_THROW(FlightSimulator{bad}, InputError);
  bad = ProceduralOptions();
  bad.ground_path = "/nonexistent.tif";
  EXPECT_THROW(FlightSimulator{bad}, InputError);
}

TEST(Simulator, RendersRealGroundRaster) {
  SynthOptions o;
  o.ground_path = testing::SharedDataPath("geotiff/UTM2GTIF.tiff");
  o.frame_count = 16;
  FlightSimulator sim(o);
  // Chicago: the raster's centre is the origin.
  EXPECT_NEAR(sim.frame().origin_lat_deg(), 41.88, 0.1);
  EXPECT_NEAR(sim.frame().origin_lon_deg(), -87.63, 0.1);
  const SimFrame f = sim.Render(8);
  cv::Scalar mean, sd;
  cv::meanStdDev(f.image, mean, sd);
  EXPECT_GT(sd[0], 1000.0);  // Textured, in counts of 65535.
  EXPECT_GT(mean[0], 10000.0);
  EXPECT_LT(mean[0], 55000.0);
}

}  // namespace
}  // namespace irmosaic
