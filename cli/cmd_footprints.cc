// `irmosaic footprints`: where each POS record's frame lands on the ground, as GeoJSON.
#include <fstream>
#include <iostream>
#include <nlohmann/json.hpp>

#include "args.h"
#include "commands.h"
#include "irmosaic/camera.h"
#include "irmosaic/frame_geometry.h"
#include "irmosaic/local_frame.h"
#include "irmosaic/pos.h"

namespace irmosaic::cli {

int RunFootprints(int argc, char** argv) {
  Args args("footprints",
            "Computes each POS record's frame footprint (rays meet the ellipsoid at the ground\n"
            "height) and prints a GeoJSON FeatureCollection of polygons in WGS84 lon/lat.");
  args.Option("--pos", "POS log, CSV (docs/formats.md)", std::nullopt, "FILE");
  args.Option("--camera", "camera file, JSON (docs/formats.md)", std::nullopt, "FILE");
  args.Option("--ground-height", "ground ellipsoidal height, metres", "0", "M");
  args.Option("--gsd", "mosaic ground sample distance, metres", "0.5", "M");
  args.Option("--every", "use every Nth POS record", "1", "N");
  args.Option("--output", "write GeoJSON here instead of standard output", "", "FILE");
  int exit_code = 0;
  if (!args.Parse(argc, argv, &exit_code)) return exit_code;

  const PosTrack track = PosTrack::LoadCsv(args.Get("--pos"));
  const CameraModel camera = CameraModel::LoadJson(args.Get("--camera"));
  const FlatGround ground(args.GetDouble("--ground-height"));
  const MosaicGrid grid{args.GetDouble("--gsd")};
  const int every = std::max(1, args.GetInt("--every"));
  const PosRecord& first = track.records().front();
  const LocalFrame frame(first.lat_deg, first.lon_deg);
  PlaneToGeographic to_geographic(frame);

  nlohmann::json features = nlohmann::json::array();
  int mapped = 0, refused = 0;
  for (size_t i = 0; i < track.records().size(); i += every) {
    const PosRecord& record = track.records()[i];
    const FrameGeometry geometry =
        ComputeFrameGeometry(camera, PoseFromRecord(record), frame, grid, ground);
    nlohmann::json properties = {{"index", i}, {"time_s", record.time_s}};
    if (!geometry.ok) {
      ++refused;
      std::cerr << "footprints: record " << i << " (time " << record.time_s
                << " s): " << geometry.problem << "\n";
      continue;
    }
    ++mapped;
    nlohmann::json ring = nlohmann::json::array();
    for (int c = 0; c <= 4; ++c) {
      const Eigen::Vector2d ll = to_geographic.LatLonFromPlane(geometry.footprint_m[c % 4]);
      ring.push_back({ll.y(), ll.x()});
    }
    properties["homography_fit_max_px"] = geometry.fit_max_px;
    features.push_back({{"type", "Feature"},
                        {"properties", properties},
                        {"geometry", {{"type", "Polygon"}, {"coordinates", {ring}}}}});
  }
  const nlohmann::json collection = {{"type", "FeatureCollection"}, {"features", features}};
  if (args.Get("--output").empty()) {
    std::cout << collection.dump(1) << "\n";
  } else {
    std::ofstream out(args.Get("--output"));
    out << collection.dump(1) << "\n";
    if (!out) {
      std::cerr << "footprints: cannot write " << args.Get("--output") << "\n";
      return 1;
    }
  }
  std::cerr << "footprints: " << mapped << " frames mapped, " << refused << " refused\n";
  return refused > 0 && mapped == 0 ? 1 : 0;
}

}  // namespace irmosaic::cli
