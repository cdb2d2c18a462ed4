// The QGIS layer definition (.qlr) of a store: the mosaic with a thermal ramp, and the frames.
#include <algorithm>
#include <sstream>

#include "store_internal.h"

namespace irmosaic::store {

namespace {

std::string Escape(const std::string& text) {
  std::string out;
  for (char c : text) {
    if (c == '&') {
      out += "&amp;";
    } else if (c == '<') {
      out += "&lt;";
    } else if (c == '>') {
      out += "&gt;";
    } else if (c == '"') {
      out += "&quot;";
    } else {
      out += c;
    }
  }
  return out;
}

// "Iron" thermal palette (black, violet, red, orange, yellow, white) as positions in [0, 1].
struct RampStop {
  double at;
  const char* rgb;
};
constexpr RampStop kIronRamp[] = {{0.0, "#000000"},  {0.15, "#1f0c48"}, {0.3, "#620e8e"},
                                  {0.45, "#b01f6f"}, {0.6, "#e8471d"},  {0.75, "#fb9b06"},
                                  {0.9, "#f9e04a"},  {1.0, "#ffffff"}};

}  // namespace

bool CoveredPercentiles(const std::vector<const TileImage*>& tiles, double* lo, double* hi) {
  std::vector<float> values;
  for (const TileImage* tile : tiles) {
    cv::Mat as_float;
    tile->data.convertTo(as_float, CV_32F);
    // Every 4th sample of every 4th row is plenty for a display range.
    for (int y = 0; y < as_float.rows; y += 4) {
      const float* v = as_float.ptr<float>(y);
      const uchar* a = tile->alpha.ptr<uchar>(y);
      for (int x = 0; x < as_float.cols; x += 4) {
        if (a[x]) values.push_back(v[x]);
      }
    }
  }
  if (values.empty()) return false;
  const auto at = [&](double q) {
    auto it = values.begin() + static_cast<std::ptrdiff_t>(q * (values.size() - 1));
    std::nth_element(values.begin(), it, values.end());
    return static_cast<double>(*it);
  };
  *lo = at(0.02);
  *hi = at(0.98);
  if (*hi <= *lo) *hi = *lo + 1.0;
  return true;
}

std::string BuildQlr(const std::string& layer_name, const std::string& crs_wkt, double display_lo,
                     double display_hi, bool live) {
  // A fixed range (the store rewrites the .qlr as the data's range grows): QGIS's own
  // cumulative-cut statistics would count the uncovered zeros, which only the alpha band marks.
  const double lo = display_lo;
  const double hi = display_hi > display_lo ? display_hi : display_lo + 1.0;
  const std::string raster_id = layer_name + (live ? "_live_mosaic" : "_mosaic");
  const std::string raster_source = live ? "./manifest.json" : "./mosaic.vrt";
  const std::string raster_name = layer_name + (live ? " mosaic (live)" : " mosaic");
  const std::string frames_id = layer_name + "_frames";
  const std::string srs =
      "<srs><spatialrefsys><wkt>" + Escape(crs_wkt) + "</wkt></spatialrefsys></srs>";
  std::ostringstream x;
  x << "<!DOCTYPE qgis-layer-definition>\n<qlr>\n"
    << "  <layer-tree-group expanded=\"1\" name=\"\" checked=\"Qt::Checked\">\n"
    << "    <layer-tree-layer providerKey=\"ogr\" expanded=\"1\" id=\"" << frames_id << "\" name=\""
    << Escape(layer_name) << " frames\" checked=\"Qt::Checked\" "
    << "source=\"./frames.gpkg|layername=frames\"/>\n"
    << "    <layer-tree-layer providerKey=\"gdal\" expanded=\"1\" id=\"" << raster_id
    << "\" name=\"" << Escape(raster_name) << "\" checked=\"Qt::Checked\" "
    << "source=\"" << raster_source << "\"/>\n"
    << "  </layer-tree-group>\n  <maplayers>\n";
  // The mosaic: repainted every 2 s (1 s live), alpha band for coverage, thermal ramp.
  x << "    <maplayer type=\"raster\" autoRefreshEnabled=\"1\" autoRefreshTime=\""
    << (live ? 1000 : 2000)
    << "\" "
       "hasScaleBasedVisibilityFlag=\"0\" minScale=\"1e+08\" maxScale=\"0\" "
       "styleCategories=\"AllStyleCategories\">\n"
    << "      <id>" << raster_id << "</id>\n      <datasource>" << raster_source
    << "</datasource>\n"
    << "      <layername>" << Escape(raster_name) << "</layername>\n      " << srs
    << "\n      <provider>gdal</provider>\n"
    << "      <pipe>\n"
    << "        <rasterrenderer type=\"singlebandpseudocolor\" band=\"1\" alphaBand=\"2\" "
       "opacity=\"1\" nodataColor=\"\" classificationMin=\""
    << lo << "\" classificationMax=\"" << hi << "\">\n"
    << "          <minMaxOrigin><limits>None</limits><extent>WholeRaster</extent>"
       "<statAccuracy>Estimated</statAccuracy><cumulativeCutLower>0.02</cumulativeCutLower>"
       "<cumulativeCutUpper>0.98</cumulativeCutUpper><stdDevFactor>2</stdDevFactor>"
       "</minMaxOrigin>\n"
    << "          <rastershader><colorrampshader colorRampType=\"INTERPOLATED\" "
       "classificationMode=\"2\" clip=\"0\" minimumValue=\""
    << lo << "\" maximumValue=\"" << hi << "\">\n";
  for (const RampStop& stop : kIronRamp) {
    const double value = lo + stop.at * (hi - lo);
    x << "            <item color=\"" << stop.rgb << "\" alpha=\"255\" value=\"" << value
      << "\" label=\"" << value << "\"/>\n";
  }
  x << "          </colorrampshader></rastershader>\n        </rasterrenderer>\n"
    << "        <brightnesscontrast brightness=\"0\" contrast=\"0\" gamma=\"1\"/>\n"
    << "        <huesaturation saturation=\"0\" grayscaleMode=\"0\" colorizeOn=\"0\"/>\n"
    << "        <rasterresampler maxOversampling=\"2\" zoomedOutResampler=\"bilinear\"/>\n"
    << "      </pipe>\n      <blendMode>0</blendMode>\n    </maplayer>\n";
  // The frame footprints: outlines only, refreshed with the mosaic.
  x << "    <maplayer type=\"vector\" geometry=\"Polygon\" wkbType=\"Polygon\" "
       "autoRefreshEnabled=\"1\" autoRefreshTime=\"2000\" readOnly=\"1\" "
       "styleCategories=\"AllStyleCategories\" hasScaleBasedVisibilityFlag=\"0\" "
       "minScale=\"1e+08\" maxScale=\"0\">\n"
    << "      <id>" << frames_id << "</id>\n"
    << "      <datasource>./frames.gpkg|layername=frames</datasource>\n"
    << "      <layername>" << Escape(layer_name) << " frames</layername>\n      " << srs
    << "\n      <provider encoding=\"UTF-8\">ogr</provider>\n"
    << "      <renderer-v2 type=\"singleSymbol\" symbollevels=\"0\" forceraster=\"0\" "
       "enableorderby=\"0\">\n        <symbols>\n"
    << "          <symbol type=\"fill\" name=\"0\" alpha=\"1\" clip_to_extent=\"1\" "
       "force_rhr=\"0\">\n"
    << "            <layer class=\"SimpleFill\" enabled=\"1\" locked=\"0\" pass=\"0\">\n"
    << "              <Option type=\"Map\">\n"
    << "                <Option name=\"color\" type=\"QString\" value=\"0,0,0,0\"/>\n"
    << "                <Option name=\"style\" type=\"QString\" value=\"no\"/>\n"
    << "                <Option name=\"outline_color\" type=\"QString\" "
       "value=\"0,200,255,255\"/>\n"
    << "                <Option name=\"outline_style\" type=\"QString\" value=\"solid\"/>\n"
    << "                <Option name=\"outline_width\" type=\"QString\" value=\"0.2\"/>\n"
    << "                <Option name=\"outline_width_unit\" type=\"QString\" value=\"MM\"/>\n"
    << "              </Option>\n            </layer>\n          </symbol>\n"
    << "        </symbols>\n      </renderer-v2>\n"
    << "      <blendMode>0</blendMode>\n    </maplayer>\n";
  x << "  </maplayers>\n</qlr>\n";
  return x.str();
}

}  // namespace irmosaic::store
