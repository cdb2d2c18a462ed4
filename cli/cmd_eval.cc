// `irmosaic eval`: scores runs' placements (and pair registrations) against a truth.
#include <algorithm>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <iomanip>
#include <iostream>
#include <set>
#include <vector>

#include "args.h"
#include "commands.h"
#include "irmosaic/evaluator.h"

namespace irmosaic::cli {

int RunEval(int argc, char** argv) {
  Args args("eval",
            "Scores placements files (RUN.json ...) against a truth (truth.json from\n"
            "`irmosaic synth`): per-frame RMSE of a grid of each frame's pixels in truth mosaic\n"
            "pixels and metres, statistics, absolute georeference error, optional pairwise\n"
            "registrations; writes JSON and a PNG plot of RMSE against frame index.\n"
            "usage: irmosaic eval --truth truth.json RUN.json [RUN2.json ...] [options]");
  args.Option("--truth", "truth placements (truth.json)", std::nullopt, "FILE");
  args.Option("--pairs", "pair registrations to score, JSON", "", "FILE");
  args.Option("--json", "write the scores here", "", "FILE");
  args.Option("--plot", "write the RMSE-vs-index plot here (PNG)", "", "FILE");
  args.Option("--title", "plot title", "", "TEXT");
  args.Option("--grid", "points per image side", "9", "N");
  args.Option("--width", "image width (default: the truth's image_width, else 640)", "", "PX");
  args.Option("--height", "image height (default: the truth's image_height, else 512)", "", "PX");
  // Runs are any number of positional files; the parser takes options only.
  const std::set<std::string> with_value = {"--truth", "--pairs", "--json",  "--plot",
                                            "--title", "--grid",  "--width", "--height"};
  std::vector<char*> option_argv;
  std::vector<std::string> runs;
  for (int i = 0; i < argc; ++i) {
    const std::string token = argv[i];
    if (token.rfind("-", 0) == 0) {
      option_argv.push_back(argv[i]);
      if (with_value.count(token) && i + 1 < argc) option_argv.push_back(argv[++i]);
    } else {
      runs.push_back(token);
    }
  }
  int exit_code = 0;
  if (!args.Parse(static_cast<int>(option_argv.size()), option_argv.data(), &exit_code)) {
    return exit_code;
  }
  EvaluatorOptions options;
  options.grid = args.GetInt("--grid");
  if (!args.Get("--width").empty()) options.width = args.GetInt("--width");
  if (!args.Get("--height").empty()) options.height = args.GetInt("--height");
  const Evaluator evaluator(Placements::LoadJson(args.Get("--truth")), options);
  std::vector<PlacementScore> scores;
  std::cout << std::fixed << std::setprecision(3);
  for (const std::string& run : runs) {
    std::string name = std::filesystem::path(run).stem().string();
    const std::string parent = std::filesystem::path(run).parent_path().filename().string();
    if (!parent.empty()) name = parent + "/" + name;
    scores.push_back(evaluator.ScorePlacements(Placements::LoadJson(run), name));
    const PlacementScore& s = scores.back();
    std::cout << name << ": " << s.frames_scored << "/" << s.frames_in_truth
              << " frames; RMSE px mean " << s.rmse_px.mean << ", median " << s.rmse_px.median
              << ", p95 " << s.rmse_px.p95 << ", max " << s.rmse_px.max << "; within 1 px "
              << 100.0 * s.rmse_px.share_within_1px << " %; georeference offset "
              << s.georeference_offset_m.norm() << " m; absolute RMSE " << s.absolute_rmse_m
              << " m; relative RMSE " << s.relative_rmse_px << " px\n";
    // The frames to look at first: the worst five, by RMSE.
    const std::vector<FrameScore> worst = WorstFrames(s, 5);
    if (!worst.empty()) {
      std::cout << "  worst frames (index: RMSE px):";
      for (size_t k = 0; k < worst.size(); ++k) {
        std::cout << (k ? ", " : " ") << worst[k].index << ": " << worst[k].rmse_px;
      }
      std::cout << "\n";
    }
  }
  PairsScore pairs;
  const bool have_pairs = !args.Get("--pairs").empty();
  if (have_pairs) {
    pairs = evaluator.ScorePairs(LoadPairsJson(args.Get("--pairs")));
    std::cout << "pairs: " << pairs.pairs_scored << "/" << pairs.pairs_given
              << " scored; RMSE px mean " << pairs.rmse_px.mean << ", median "
              << pairs.rmse_px.median << ", p95 " << pairs.rmse_px.p95 << ", max "
              << pairs.rmse_px.max << "; within 1 px " << 100.0 * pairs.rmse_px.share_within_1px
              << " %\n";
  }
  if (runs.empty() && !have_pairs) {
    std::cerr << "irmosaic eval: nothing to score. Fix: give RUN.json files and/or --pairs\n";
    return 2;
  }
  if (!args.Get("--json").empty()) {
    std::ofstream out(args.Get("--json"));
    out << ScoresToJson(scores, have_pairs ? &pairs : nullptr) << "\n";
    if (!out) {
      std::cerr << "irmosaic eval: cannot write " << args.Get("--json") << "\n";
      return 1;
    }
  }
  if (!args.Get("--plot").empty() && !scores.empty()) {
    PlotRmseVsIndex(scores, args.Get("--plot"), args.Get("--title"));
  }
  return 0;
}

}  // namespace irmosaic::cli
