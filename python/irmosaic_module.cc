// Python bindings of the pipeline object (Mosaicker) and its inputs, for GIS pipelines.
// Images cross as numpy arrays; errors as irmosaic.InputError (a ValueError) and
// irmosaic.OutputError (an OSError) carrying the library's messages. docs/api.md.

#include <pybind11/eigen.h>
#include <pybind11/numpy.h>
#include <pybind11/pybind11.h>
#include <pybind11/stl.h>

#include <cstring>
#include <limits>
#include <memory>
#include <optional>
#include <stdexcept>
#include <string>
#include <vector>

#include "irmosaic/camera.h"
#include "irmosaic/error.h"
#include "irmosaic/mosaicker.h"
#include "irmosaic/pos.h"
#include "irmosaic/tile_store.h"
#include "irmosaic/version.h"

namespace py = pybind11;

namespace irmosaic {
namespace {

// numpy dtype -> OpenCV depth; throws TypeError naming the accepted types.
int CvDepthOfDtype(const py::array& array, const char* what) {
  if (array.dtype().is(py::dtype::of<uint8_t>())) return CV_8U;
  if (array.dtype().is(py::dtype::of<uint16_t>())) return CV_16U;
  if (array.dtype().is(py::dtype::of<float>())) return CV_32F;
  throw py::type_error(std::string(what) + ": dtype " + py::str(array.dtype()).cast<std::string>() +
                       " is not supported; use numpy.uint8, numpy.uint16 or numpy.float32");
}

// A copy of a 2-D, C-contiguous numpy array as a one-channel cv::Mat (the copy lets Push run
// without the GIL while Python may change the array).
cv::Mat MatFromArray(const py::array& array, const char* what) {
  const int depth = CvDepthOfDtype(array, what);
  if (array.ndim() != 2) {
    throw py::value_error(std::string(what) + ": expected a 2-D array (rows, cols), got " +
                          std::to_string(array.ndim()) + " dimensions");
  }
  if (!(array.flags() & py::array::c_style)) {
    throw py::value_error(std::string(what) +
                          ": the array is not C-contiguous; pass numpy.ascontiguousarray(a)");
  }
  const auto rows = array.shape(0);
  const auto cols = array.shape(1);
  if (rows <= 0 || cols <= 0 || rows > std::numeric_limits<int>::max() ||
      cols > std::numeric_limits<int>::max()) {
    throw py::value_error(std::string(what) + ": empty or oversized array");
  }
  cv::Mat mat(static_cast<int>(rows), static_cast<int>(cols), CV_MAKETYPE(depth, 1));
  std::memcpy(mat.data, array.data(), mat.total() * mat.elemSize());
  return mat;
}

// A one-channel cv::Mat (8U, 16U or 32F) as a new numpy array.
py::array ArrayFromMat(const cv::Mat& mat) {
  const cv::Mat m = mat.isContinuous() ? mat : mat.clone();
  std::vector<py::ssize_t> shape = {m.rows, m.cols};
  py::array out;
  switch (m.depth()) {
    case CV_8U:
      out = py::array_t<uint8_t>(shape);
      break;
    case CV_16U:
      out = py::array_t<uint16_t>(shape);
      break;
    case CV_32F:
      out = py::array_t<float>(shape);
      break;
    default:
      throw std::runtime_error("unexpected image depth from the store");
  }
  std::memcpy(out.mutable_data(), m.data, m.total() * m.elemSize());
  return out;
}

py::dict PlacementToDict(const FramePlacement& p) {
  py::dict d;
  d["index"] = p.index;
  d["time_s"] = p.time_s;
  d["mosaic_from_image"] = Eigen::Matrix3d(p.mosaic_from_image);
  d["pos_mosaic_from_image"] = Eigen::Matrix3d(p.pos_mosaic_from_image);
  d["pos_only"] = p.pos_only;
  d["neighbours"] = p.neighbours;
  d["inliers"] = p.inliers;
  d["residual_px"] = p.residual_px;
  d["gain"] = p.gain;
  d["offset"] = p.offset;
  d["optimized_times"] = p.optimized_times;
  d["note"] = p.note;
  return d;
}

py::dict RecordToDict(const PosRecord& r) {
  py::dict d;
  d["time_s"] = r.time_s;
  d["lat_deg"] = r.lat_deg;
  d["lon_deg"] = r.lon_deg;
  d["height_m"] = r.height_m;
  d["roll_deg"] = r.roll_deg;
  d["pitch_deg"] = r.pitch_deg;
  d["yaw_deg"] = r.yaw_deg;
  d["gimbal_roll_deg"] = r.gimbal_roll_deg;
  d["gimbal_pitch_deg"] = r.gimbal_pitch_deg;
  d["gimbal_yaw_deg"] = r.gimbal_yaw_deg;
  return d;
}

// A POS record from any mapping with the CSV column names (docs/formats.md); the attitude
// columns are required as in the CSV, the gimbal ones default to 0.
PosRecord RecordFromMapping(const py::handle& item, size_t position, const std::string& source,
                            bool time_required = true) {
  const std::string where = source + " record " + std::to_string(position);
  if (!py::isinstance<py::dict>(item) && !py::hasattr(item, "__getitem__")) {
    throw py::type_error(where + ": expected a dict-like record with keys such as 'time_s'");
  }
  const py::object record = py::reinterpret_borrow<py::object>(item);
  auto contains = [&](const char* key) { return record.attr("__contains__")(key).cast<bool>(); };
  auto get = [&](const char* key, bool required) -> double {
    if (!contains(key)) {
      if (required) {
        throw py::key_error(where + ": missing field '" + key +
                            "' (required: time_s, lat_deg, lon_deg, height_m, roll_deg, "
                            "pitch_deg, yaw_deg)");
      }
      return 0.0;
    }
    try {
      return record[py::str(key)].cast<double>();
    } catch (const py::cast_error&) {
      throw py::type_error(where + ": field '" + key + "' is not a number");
    }
  };
  PosRecord r;
  r.time_s = get("time_s", time_required);
  r.lat_deg = get("lat_deg", true);
  r.lon_deg = get("lon_deg", true);
  r.height_m = get("height_m", true);
  r.roll_deg = get("roll_deg", true);
  r.pitch_deg = get("pitch_deg", true);
  r.yaw_deg = get("yaw_deg", true);
  r.gimbal_roll_deg = get("gimbal_roll_deg", false);
  r.gimbal_pitch_deg = get("gimbal_pitch_deg", false);
  r.gimbal_yaw_deg = get("gimbal_yaw_deg", false);
  return r;
}

const char* ModeName(TileStoreOptions::Mode mode) {
  switch (mode) {
    case TileStoreOptions::Mode::kCreate:
      return "create";
    case TileStoreOptions::Mode::kOverwrite:
      return "overwrite";
    case TileStoreOptions::Mode::kResume:
      return "resume";
  }
  return "create";
}

TileStoreOptions::Mode ModeFromName(const std::string& name) {
  if (name == "create") return TileStoreOptions::Mode::kCreate;
  if (name == "overwrite") return TileStoreOptions::Mode::kOverwrite;
  if (name == "resume") return TileStoreOptions::Mode::kResume;
  throw py::value_error("mode '" + name + "' is not one of 'create', 'overwrite', 'resume'");
}

py::dict FrameRecordToDict(const FrameRecord& r) {
  py::dict d;
  d["index"] = r.index;
  d["time_s"] = r.time_s;
  Eigen::Matrix<double, 4, 2, Eigen::RowMajor> footprint;
  for (int k = 0; k < 4; ++k) footprint.row(k) = r.footprint_m[k].transpose();
  d["footprint_m"] = footprint;
  d["pos_only"] = r.pos_only;
  d["residual_px"] = r.residual_px;
  d["inliers"] = r.inliers;
  d["status"] = r.status;
  return d;
}

py::dict PushResultToDict(const PushResult& result) {
  py::dict d;
  d["placed"] = result.placed();
  d["reason"] = result.reason;
  d["placement"] =
      result.placed() ? py::object(PlacementToDict(result.placement)) : py::object(py::none());
  return d;
}

TileStore& StoreOf(Mosaicker& m) {
  TileStore* store = m.store();
  if (store == nullptr) {
    throw std::runtime_error("the store is not open yet: no frame has been placed");
  }
  return *store;
}

}  // namespace
}  // namespace irmosaic

PYBIND11_MODULE(irmosaic, m) {
  using namespace irmosaic;
  m.doc() = "irmosaic: georeferenced mosaics from oblique infrared video with POS";
  m.attr("__version__") = IRMOSAIC_VERSION_STRING;

  // Library exceptions: messages are complete sentences naming the input and the fix.
  static py::exception<Error> error_type(m, "Error", PyExc_RuntimeError);
  static py::exception<InputError> input_error_type(m, "InputError", PyExc_ValueError);
  static py::exception<OutputError> output_error_type(m, "OutputError", PyExc_OSError);
  py::register_exception_translator([](std::exception_ptr p) {
    try {
      if (p) std::rethrow_exception(p);
    } catch (const InputError& e) {
      input_error_type(e.what());
    } catch (const OutputError& e) {
      output_error_type(e.what());
    } catch (const Error& e) {
      error_type(e.what());
    }
  });

  py::class_<CameraModel>(m, "CameraModel",
                          "Pinhole camera with OpenCV distortion (docs/formats.md).")
      .def(py::init<>())
      .def_static("load_json", &CameraModel::LoadJson, py::arg("path"),
                  "Reads a camera JSON file; raises InputError naming the file and field.")
      .def_static("default_infrared", &DefaultInfraredCamera, py::arg("fx_px") = 2400.0,
                  "The project's default 640x512 sensor.")
      .def("save_json", &CameraModel::SaveJson, py::arg("path"))
      .def("validate", &CameraModel::Validate, py::arg("source") = "camera")
      .def_readwrite("width", &CameraModel::width)
      .def_readwrite("height", &CameraModel::height)
      .def_readwrite("fx", &CameraModel::fx)
      .def_readwrite("fy", &CameraModel::fy)
      .def_readwrite("cx", &CameraModel::cx)
      .def_readwrite("cy", &CameraModel::cy)
      .def_readwrite("distortion", &CameraModel::distortion)
      .def_readwrite("boresight_deg", &CameraModel::boresight_deg)
      .def_readwrite("lever_arm_m", &CameraModel::lever_arm_m)
      .def("__repr__", [](const CameraModel& c) {
        return "CameraModel(" + std::to_string(c.width) + "x" + std::to_string(c.height) +
               ", fx=" + std::to_string(c.fx) + ", fy=" + std::to_string(c.fy) + ")";
      });

  py::class_<PosTrack>(m, "PosTrack", "Time-ordered POS log interpolated to frame times.")
      .def_static(
          "load_csv",
          [](const std::string& path, double max_gap_s) {
            PosTrack::Options options;
            options.max_gap_s = max_gap_s;
            return PosTrack::LoadCsv(path, options);
          },
          py::arg("path"), py::arg("max_gap_s") = 1.0,
          "Reads the POS CSV of docs/formats.md; raises InputError naming file, line, column.")
      .def_static(
          "from_records",
          [](const py::iterable& records, const std::string& source, double max_gap_s) {
            std::vector<PosRecord> parsed;
            size_t position = 0;
            for (const py::handle item : records) {
              parsed.push_back(RecordFromMapping(item, position++, source));
            }
            PosTrack::Options options;
            options.max_gap_s = max_gap_s;
            return PosTrack::FromRecords(std::move(parsed), source, options);
          },
          py::arg("records"), py::arg("source") = "records", py::arg("max_gap_s") = 1.0,
          "Builds from dicts with the CSV column names (gimbal_* default to 0).")
      .def("write_csv", &PosTrack::WriteCsv, py::arg("path"))
      .def("records",
           [](const PosTrack& t) {
             py::list out;
             for (const PosRecord& r : t.records()) out.append(RecordToDict(r));
             return out;
           })
      .def(
          "pose_at",
          [](const PosTrack& t, double time_s) -> py::object {
            const PoseLookup lookup = t.At(time_s);
            if (!lookup.ok()) return py::none();
            py::dict d;
            d["lat_deg"] = lookup.pose.lat_deg;
            d["lon_deg"] = lookup.pose.lon_deg;
            d["height_m"] = lookup.pose.height_m;
            return d;
          },
          py::arg("time_s"), "Interpolated position at time_s, or None outside the log.")
      .def("__len__", [](const PosTrack& t) { return t.records().size(); });

  py::class_<FusionOptions>(m, "FusionOptions", "Map fusion and global optimization settings.")
      .def(py::init<>())
      .def_readwrite("window_frames", &FusionOptions::window_frames)
      .def_readwrite("solve_every_frames", &FusionOptions::solve_every_frames)
      .def_readwrite("short_window_frames", &FusionOptions::short_window_frames)
      .def_readwrite("full_window_every", &FusionOptions::full_window_every)
      .def_readwrite("solve_iterations", &FusionOptions::solve_iterations)
      .def_readwrite("max_neighbours", &FusionOptions::max_neighbours)
      .def_readwrite("max_ties_per_pair", &FusionOptions::max_ties_per_pair)
      .def_readwrite("min_overlap_fraction", &FusionOptions::min_overlap_fraction)
      .def_readwrite("pos_sigma_px", &FusionOptions::pos_sigma_px)
      .def_readwrite("tie_sigma_px", &FusionOptions::tie_sigma_px)
      .def_readwrite("robust_scale", &FusionOptions::robust_scale)
      .def_readwrite("rerender_threshold_px", &FusionOptions::rerender_threshold_px)
      .def_readwrite("max_rerenders_per_solve", &FusionOptions::max_rerenders_per_solve)
      .def_readwrite("max_output_backlog_s", &FusionOptions::max_output_backlog_s)
      .def_readwrite("rerender_settled_frames", &FusionOptions::rerender_settled_frames)
      .def_readwrite("settled_rerender_threshold_px", &FusionOptions::settled_rerender_threshold_px)
      .def_readwrite("optimizer_nice", &FusionOptions::optimizer_nice)
      .def_readwrite("optimize", &FusionOptions::optimize)
      .def_readwrite("compensate_gain", &FusionOptions::compensate_gain)
      .def_readwrite("feather_px", &FusionOptions::feather_px)
      .def_readwrite("render", &FusionOptions::render);

  py::class_<MosaickerOptions>(m, "MosaickerOptions", "Configuration of a mosaicking run.")
      .def(py::init<>())
      .def(py::init([](const std::string& store_path, const std::string& mode, double gsd_m) {
             MosaickerOptions o;
             o.store_path = store_path;
             o.mode = ModeFromName(mode);
             o.gsd_m = gsd_m;
             return o;
           }),
           py::arg("store_path"), py::arg("mode") = "create", py::arg("gsd_m") = 0.0)
      .def_readwrite("store_path", &MosaickerOptions::store_path)
      .def_property(
          "mode", [](const MosaickerOptions& o) { return std::string(ModeName(o.mode)); },
          [](MosaickerOptions& o, const std::string& name) { o.mode = ModeFromName(name); },
          "'create', 'overwrite' or 'resume'")
      .def_readwrite("gsd_m", &MosaickerOptions::gsd_m)
      .def_readwrite("origin_lat_deg", &MosaickerOptions::origin_lat_deg)
      .def_readwrite("origin_lon_deg", &MosaickerOptions::origin_lon_deg)
      .def_readwrite("ground_height_m", &MosaickerOptions::ground_height_m)
      .def_readwrite("pos_position_sigma_m", &MosaickerOptions::pos_position_sigma_m)
      .def_readwrite("pos_attitude_sigma_deg", &MosaickerOptions::pos_attitude_sigma_deg)
      .def_readwrite("search_radius_px", &MosaickerOptions::search_radius_px)
      .def_readwrite("wide_search_radius_px", &MosaickerOptions::wide_search_radius_px)
      .def_readwrite("max_range_m", &MosaickerOptions::max_range_m)
      .def_readwrite("publish_interval_s", &MosaickerOptions::publish_interval_s)
      .def_readwrite("tile_size", &MosaickerOptions::tile_size)
      .def_readwrite("compression", &MosaickerOptions::compression)
      .def_readwrite("planned_extent", &MosaickerOptions::planned_extent)
      .def_readwrite("registration_threads", &MosaickerOptions::registration_threads)
      .def_readwrite("heap_trim_interval_frames", &MosaickerOptions::heap_trim_interval_frames)
      .def_readwrite("tune_heap", &MosaickerOptions::tune_heap)
      .def_readwrite("max_cached_tiles", &MosaickerOptions::max_cached_tiles)
      .def_readwrite("writer_nice", &MosaickerOptions::writer_nice)
      .def_readwrite("images_in_memory", &MosaickerOptions::images_in_memory)
      .def_readwrite("fusion", &MosaickerOptions::fusion)
      .def("validate", [](const MosaickerOptions& o) {
        std::string error;
        if (!o.IsValid(&error)) throw py::value_error(error);
      });

  py::class_<Mosaicker>(m, "Mosaicker",
                        "The whole pipeline: push frames with a POS track, read the live mosaic.")
      .def(py::init([](MosaickerOptions options, CameraModel camera, std::optional<PosTrack> pos) {
             return std::make_unique<Mosaicker>(std::move(options), std::move(camera),
                                                pos ? std::move(*pos) : PosTrack());
           }),
           py::arg("options"), py::arg("camera"), py::arg("pos") = py::none(),
           "pos None: poses come with each push (then set origin_lat_deg, origin_lon_deg and "
           "gsd_m in the options).")
      .def(
          "push",
          [](Mosaicker& self, int64_t index, double time_s, const py::array& image,
             const py::object& pose) {
            const cv::Mat mat = MatFromArray(image, "image");
            std::optional<Pose> given;
            if (!pose.is_none()) given = PoseFromRecord(RecordFromMapping(pose, 0, "pose", false));
            PushResult result;
            {
              py::gil_scoped_release release;
              result =
                  given ? self.Push(index, time_s, *given, mat) : self.Push(index, time_s, mat);
            }
            return PushResultToDict(result);
          },
          py::arg("index"), py::arg("time_s"), py::arg("image"), py::arg("pose") = py::none(),
          "Places a frame (2-D uint8/uint16/float32 array) taken at time_s; its pose from the "
          "POS track, or from `pose` (a dict with the POS CSV fields, time_s optional). Returns "
          "{'placed', 'reason', 'placement'}; a frame that cannot be placed is skipped with a "
          "reason.")
      .def(
          "on_published",
          [](Mosaicker& self, const py::object& callback) {
            if (callback.is_none()) {
              self.OnPublished(nullptr);
              return;
            }
            if (!PyCallable_Check(callback.ptr())) {
              throw py::type_error("on_published: expected a callable taking the generation");
            }
            auto holder = std::make_shared<py::object>(callback);
            self.OnPublished([holder](int64_t generation) {
              py::gil_scoped_acquire acquire;
              (*holder)(generation);
            });
          },
          py::arg("callback"),
          "callback(generation) after each publish, called from push/finish/request_publish "
          "(the calling thread); None removes it.")
      .def("published_generation", &Mosaicker::published_generation,
           "Generation last published on disk (0: none yet).")
      .def("wait_published", &Mosaicker::WaitPublished, py::arg("generation"),
           py::call_guard<py::gil_scoped_release>(),
           "Blocks until that generation is on disk; raises OutputError if the store failed.")
      .def(
          "frame_records",
          [](const Mosaicker& self) {
            py::list out;
            for (const FrameRecord& r : self.FrameRecords()) out.append(FrameRecordToDict(r));
            return out;
          },
          "Per-frame records as in frames.gpkg: [{'index', 'time_s', 'footprint_m' (4x2, "
          "mosaic plane metres), 'pos_only', 'residual_px', 'inliers', 'status'}].")
      .def("finish", &Mosaicker::Finish, py::call_guard<py::gil_scoped_release>(),
           "Last solve, re-render and final publish.")
      .def("request_publish", &Mosaicker::RequestPublish,
           "Asks the store to publish now (non-blocking).")
      .def("placements",
           [](const Mosaicker& self) {
             py::list out;
             for (const FramePlacement& p : self.Placements()) out.append(PlacementToDict(p));
             return out;
           })
      .def("write_placements", &Mosaicker::WritePlacements, py::arg("path"))
      .def("summary",
           [](const Mosaicker& self) {
             const MosaickerSummary s = self.summary();
             py::dict d;
             d["frames_pushed"] = s.frames_pushed;
             d["frames_placed"] = s.frames_placed;
             d["frames_registered"] = s.frames_registered;
             d["frames_pos_only"] = s.frames_pos_only;
             d["frames_skipped"] = s.frames_skipped;
             d["generations_published"] = s.generations_published;
             d["publish_latency_p50_s"] = s.publish_latency_p50_s;
             d["publish_latency_p99_s"] = s.publish_latency_p99_s;
             d["publish_latency_max_s"] = s.publish_latency_max_s;
             d["gsd_m"] = s.gsd_m;
             d["origin_lat_deg"] = s.origin_lat_deg;
             d["origin_lon_deg"] = s.origin_lon_deg;
             return d;
           })
      .def(
          "bounds",
          [](Mosaicker& self) {
            const cv::Rect r = StoreOf(self).level0_bounds_px();
            return py::make_tuple(r.x, r.y, r.width, r.height);
          },
          "Painted level-0 extent as (col, row, width, height) in mosaic pixels.")
      .def("georeference",
           [](Mosaicker& self) {
             const StoreGeoreference& g = self.georeference();
             py::dict d;
             d["origin_lat_deg"] = g.origin_lat_deg;
             d["origin_lon_deg"] = g.origin_lon_deg;
             d["gsd_m"] = g.gsd_m;
             d["crs_wkt"] = g.crs_wkt;
             return d;
           })
      .def(
          "read_window",
          [](Mosaicker& self, int64_t col, int64_t row, int64_t width, int64_t height) {
            if (width <= 0 || height <= 0 || width > 65536 || height > 65536) {
              throw py::value_error("read_window: width and height must be in 1..65536, got " +
                                    std::to_string(width) + " x " + std::to_string(height));
            }
            const int64_t limit = std::numeric_limits<int>::max() / 2;
            if (col < -limit || col > limit || row < -limit || row > limit) {
              throw py::value_error("read_window: col/row out of range");
            }
            StoreOf(self);  // RuntimeError before the first placed frame.
            MosaicWindow window;
            {
              py::gil_scoped_release release;
              window = self.ReadWindow(cv::Rect(static_cast<int>(col), static_cast<int>(row),
                                                static_cast<int>(width), static_cast<int>(height)));
            }
            const std::array<double, 6>& gt = window.geotransform;
            return py::make_tuple(ArrayFromMat(window.image), ArrayFromMat(window.coverage),
                                  py::make_tuple(gt[0], gt[1], gt[2], gt[3], gt[4], gt[5]),
                                  window.crs_wkt);
          },
          py::arg("col"), py::arg("row"), py::arg("width"), py::arg("height"),
          "Level-0 window at mosaic pixel (col, row): (image, coverage 0/255, GDAL geotransform, "
          "CRS WKT).");
}
