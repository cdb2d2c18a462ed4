// The QGIS layer definition (.qlr) of a store: the mosaic with a thermal ramp, and the frames.
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

std::string BuildQlr(const std::string& layer_name, const std::string& crs_wkt, PixelType type) {
  // Initial range only: the renderer recomputes a 2-98 % cumulative cut of what the canvas
  // shows on every redraw, so the ramp follows the data as the mosaic grows.
  const double lo = 0.0;
  const double hi = type == PixelType::kByte ? 255.0 : type == PixelType::kUInt16 ? 65535.0 : 100.0;
  const std::string raster_id = layer_name + "_mosaic";
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
    << "\" name=\"" << Escape(layer_name) << " mosaic\" checked=\"Qt::Checked\" "
    << "source=\"./mosaic.vrt\"/>\n"
    << "  </layer-tree-group>\n  <maplayers>\n";
  // The mosaic: reloaded every 2 s, alpha band for coverage, thermal ramp.
  x << "    <maplayer type=\"raster\" autoRefreshEnabled=\"1\" autoRefreshTime=\"2000\" "
       "hasScaleBasedVisibilityFlag=\"0\" minScale=\"1e+08\" maxScale=\"0\" "
       "styleCategories=\"AllStyleCategories\">\n"
    << "      <id>" << raster_id << "</id>\n      <datasource>./mosaic.vrt</datasource>\n"
    << "      <layername>" << Escape(layer_name) << " mosaic</layername>\n      " << srs
    << "\n      <provider>gdal</provider>\n"
    << "      <pipe>\n"
    << "        <rasterrenderer type=\"singlebandpseudocolor\" band=\"1\" alphaBand=\"2\" "
       "opacity=\"1\" nodataColor=\"\" classificationMin=\""
    << lo << "\" classificationMax=\"" << hi << "\">\n"
    << "          <minMaxOrigin><limits>CumulativeCut</limits><extent>UpdatedCanvas</extent>"
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
