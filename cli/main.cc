// The `irmosaic` command line: a table of (name, function, summary) subcommands.
#include <cstring>
#include <iostream>
#include <string>

#include "commands.h"
#include "irmosaic/error.h"
#include "irmosaic/version.h"

namespace {

struct Subcommand {
  const char* name;
  int (*run)(int argc, char** argv);
  const char* summary;
};

constexpr Subcommand kSubcommands[] = {
    {"run", irmosaic::cli::RunRun, "mosaic a flight into a live georeferenced tiled store"},
    {"footprints", irmosaic::cli::RunFootprints,
     "frame footprints on the ground from a POS log and a camera file, as GeoJSON"},
    {"synth", irmosaic::cli::RunSynth, "render a simulated sweep flight with its ground truth"},
    {"eval", irmosaic::cli::RunEval, "score runs' placements against a simulator's truth"},
    {"export", irmosaic::cli::RunExport, "a store as one COG / GeoTIFF / GeoPackage in any CRS"},
    {"register", irmosaic::cli::RunRegister, "registers two images: homography and quality, JSON"},
};

void PrintUsage(std::ostream& out) {
  out << "usage: irmosaic <command> [options]   (irmosaic <command> --help for details)\n\n"
         "Real-time georeferenced mosaics from infrared video.\n\ncommands:\n";
  for (const Subcommand& s : kSubcommands) {
    out << "  " << s.name << std::string(14 - std::strlen(s.name), ' ') << s.summary << "\n";
  }
  out << "\n  --version     print the version\n  --help        print this help\n";
}

}  // namespace

int main(int argc, char** argv) {
  if (argc < 2) {
    PrintUsage(std::cerr);
    return 2;
  }
  const std::string command = argv[1];
  if (command == "--help" || command == "-h" || command == "help") {
    PrintUsage(std::cout);
    return 0;
  }
  if (command == "--version") {
    std::cout << "irmosaic " << IRMOSAIC_VERSION_STRING << "\n";
    return 0;
  }
  for (const Subcommand& s : kSubcommands) {
    if (command == s.name) {
      try {
        return s.run(argc - 2, argv + 2);
      } catch (const irmosaic::Error& e) {
        std::cerr << "irmosaic " << command << ": error: " << e.what() << "\n";
        return 1;
      } catch (const std::exception& e) {
        std::cerr << "irmosaic " << command << ": internal error: " << e.what() << "\n";
        return 3;
      }
    }
  }
  std::cerr << "irmosaic: unknown command '" << command << "'\n\n";
  PrintUsage(std::cerr);
  return 2;
}
