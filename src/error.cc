#include "irmosaic/error.h"

#include <utility>

namespace irmosaic {

std::string SourceLocation::ToString() const {
  std::string text = input.empty() ? std::string("<input>") : input;
  if (line > 0) {
    text += ":" + std::to_string(line);
    if (column > 0) text += ":" + std::to_string(column);
  }
  if (!field.empty()) text += " (field '" + field + "')";
  return text;
}

InputError::InputError(SourceLocation where, const std::string& problem, const std::string& fix)
    : Error(where.ToString() + ": " + problem + (fix.empty() ? "" : ". Fix: " + fix)),
      where_(std::move(where)),
      problem_(problem) {}

}  // namespace irmosaic
