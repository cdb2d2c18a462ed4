#include "args.h"

#include <cstdlib>
#include <iostream>
#include <sstream>

#include "irmosaic/error.h"

namespace irmosaic::cli {

Args::Args(std::string command, std::string summary)
    : command_(std::move(command)), summary_(std::move(summary)) {}

void Args::Option(const std::string& name, const std::string& help,
                  std::optional<std::string> fallback, const std::string& metavar) {
  order_.push_back(name);
  specs_[name] = Spec{help, fallback, metavar, false, !fallback.has_value()};
}

void Args::Flag(const std::string& name, const std::string& help) {
  order_.push_back(name);
  specs_[name] = Spec{help, std::nullopt, "", true, false};
}

void Args::Positional(const std::string& name, const std::string& help) {
  positionals_.emplace_back(name, help);
}

std::string Args::Help() const {
  std::ostringstream out;
  out << "usage: irmosaic " << command_;
  for (const auto& [name, help] : positionals_) out << " " << name;
  out << " [options]\n\n" << summary_ << "\n";
  if (!positionals_.empty()) {
    out << "\narguments:\n";
    for (const auto& [name, help] : positionals_) out << "  " << name << "\n      " << help << "\n";
  }
  out << "\noptions:\n";
  for (const std::string& name : order_) {
    const Spec& spec = specs_.at(name);
    out << "  " << name << (spec.is_flag ? "" : " " + spec.metavar) << "\n      " << spec.help;
    if (spec.fallback && !spec.fallback->empty()) out << " (default: " << *spec.fallback << ")";
    if (spec.required) out << " (required)";
    out << "\n";
  }
  out << "  --help\n      show this help\n";
  return out.str();
}

bool Args::Parse(int argc, char** argv, int* exit_code) {
  size_t next_positional = 0;
  for (int i = 0; i < argc; ++i) {
    std::string token = argv[i];
    if (token == "--help" || token == "-h") {
      std::cout << Help();
      *exit_code = 0;
      return false;
    }
    if (token.size() > 1 && token[0] == '-' && !(token.size() > 1 && std::isdigit(token[1]))) {
      std::string value;
      bool has_inline = false;
      const auto eq = token.find('=');
      if (eq != std::string::npos && token.rfind("--", 0) == 0) {
        value = token.substr(eq + 1);
        token = token.substr(0, eq);
        has_inline = true;
      }
      auto it = specs_.find(token);
      if (it == specs_.end()) {
        std::cerr << "irmosaic " << command_ << ": unknown option '" << token
                  << "'. Fix: see 'irmosaic " << command_ << " --help'\n";
        *exit_code = 2;
        return false;
      }
      if (it->second.is_flag) {
        values_.emplace(token, "1");
        continue;
      }
      if (!has_inline) {
        if (i + 1 >= argc) {
          std::cerr << "irmosaic " << command_ << ": option " << token << " needs a value ("
                    << it->second.metavar << ")\n";
          *exit_code = 2;
          return false;
        }
        value = argv[++i];
      }
      values_.emplace(token, value);
      continue;
    }
    if (next_positional >= positionals_.size()) {
      std::cerr << "irmosaic " << command_ << ": unexpected argument '" << token
                << "'. Fix: see 'irmosaic " << command_ << " --help'\n";
      *exit_code = 2;
      return false;
    }
    values_.emplace(positionals_[next_positional++].first, token);
  }
  if (next_positional < positionals_.size()) {
    std::cerr << "irmosaic " << command_ << ": missing argument "
              << positionals_[next_positional].first << ". Fix: see 'irmosaic " << command_
              << " --help'\n";
    *exit_code = 2;
    return false;
  }
  for (const auto& [name, spec] : specs_) {
    if (spec.required && values_.count(name) == 0) {
      std::cerr << "irmosaic " << command_ << ": option " << name << " is required. Fix: see "
                << "'irmosaic " << command_ << " --help'\n";
      *exit_code = 2;
      return false;
    }
  }
  return true;
}

bool Args::Has(const std::string& name) const {
  if (values_.count(name)) return true;
  auto it = specs_.find(name);
  return it != specs_.end() && it->second.fallback && !it->second.fallback->empty();
}

std::string Args::Get(const std::string& name) const {
  auto range = values_.equal_range(name);
  if (range.first != range.second) return std::prev(range.second)->second;
  auto it = specs_.find(name);
  if (it != specs_.end() && it->second.fallback) return *it->second.fallback;
  return "";
}

std::vector<std::string> Args::GetAll(const std::string& name) const {
  std::vector<std::string> all;
  auto range = values_.equal_range(name);
  for (auto it = range.first; it != range.second; ++it) all.push_back(it->second);
  return all;
}

double Args::GetDouble(const std::string& name) const {
  const std::string text = Get(name);
  char* end = nullptr;
  const double value = std::strtod(text.c_str(), &end);
  if (text.empty() || end != text.c_str() + text.size()) {
    throw InputError({"command line", 0, 0, name}, "'" + text + "' is not a number",
                     "give " + name + " a number");
  }
  return value;
}

int Args::GetInt(const std::string& name) const {
  const double value = GetDouble(name);
  if (value != static_cast<int>(value)) {
    throw InputError({"command line", 0, 0, name}, "'" + Get(name) + "' is not a whole number",
                     "give " + name + " a whole number");
  }
  return static_cast<int>(value);
}

}  // namespace irmosaic::cli
