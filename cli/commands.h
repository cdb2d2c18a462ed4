#pragma once

// Subcommands of the `irmosaic` program; each lives in cli/cmd_<name>.cc and is listed in the
// table in main.cc. Each takes the arguments after its name and returns the exit code.
namespace irmosaic::cli {

int RunFootprints(int argc, char** argv);
int RunSynth(int argc, char** argv);
int RunEval(int argc, char** argv);
int RunExport(int argc, char** argv);
int RunRegister(int argc, char** argv);
int RunRun(int argc, char** argv);

}  // namespace irmosaic::cli
