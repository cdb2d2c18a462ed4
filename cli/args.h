#pragma once

#include <map>
#include <optional>
#include <string>
#include <vector>

namespace irmosaic::cli {

// A small GNU-style option parser: `--name value`, `--name=value`, `--flag`, positionals.
// Each subcommand declares its options so --help is generated and unknown options refused.
class Args {
 public:
  Args(std::string command, std::string summary);

  // Declares an option taking a value; `fallback` empty means required (unless optional).
  void Option(const std::string& name, const std::string& help, std::optional<std::string> fallback,
              const std::string& metavar = "VALUE");
  // Declares a boolean flag.
  void Flag(const std::string& name, const std::string& help);
  // Declares a positional argument (in order).
  void Positional(const std::string& name, const std::string& help);

  // Parses argv (after the subcommand). Returns false and prints help or an error on
  // --help or bad usage; *exit_code tells which (0 for --help, 2 for usage errors).
  bool Parse(int argc, char** argv, int* exit_code);

  std::string Get(const std::string& name) const;
  bool Has(const std::string& name) const;  // Option given (or with a default) / flag set.
  double GetDouble(const std::string& name) const;
  int GetInt(const std::string& name) const;
  // All values of an option that may repeat (e.g. -co KEY=VALUE).
  std::vector<std::string> GetAll(const std::string& name) const;

  std::string Help() const;

 private:
  struct Spec {
    std::string help;
    std::optional<std::string> fallback;
    std::string metavar;
    bool is_flag = false;
    bool required = false;
  };
  std::string command_, summary_;
  std::vector<std::string> order_;
  std::map<std::string, Spec> specs_;
  std::vector<std::pair<std::string, std::string>> positionals_;
  std::multimap<std::string, std::string> values_;
};

}  // namespace irmosaic::cli
