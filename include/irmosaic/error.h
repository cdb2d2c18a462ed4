#pragma once

#include <stdexcept>
#include <string>

#include "irmosaic/export.h"

namespace irmosaic {

// Base of every exception the library throws; what() is a complete, user-facing sentence.
class IRMOSAIC_EXPORT Error : public std::runtime_error {
 public:
  explicit Error(const std::string& message) : std::runtime_error(message) {}
};

// Where in an input a problem sits. Empty or zero members are left out of messages.
struct SourceLocation {
  std::string input;  // File path, or a name such as "frame 17" for pushed data.
  int line = 0;       // 1-based line number in a text input (0: not applicable).
  int column = 0;     // 1-based column number (0: not applicable).
  std::string field;  // Column or field name (empty: not applicable).

  // "pos.csv:12:3 (column 'lat')" style rendering.
  std::string ToString() const;
};

// Bad input from a caller or a file: names the input, the place, the problem and the fix.
class IRMOSAIC_EXPORT InputError : public Error {
 public:
  InputError(SourceLocation where, const std::string& problem, const std::string& fix);

  const SourceLocation& where() const { return where_; }
  const std::string& problem() const { return problem_; }

 private:
  SourceLocation where_;
  std::string problem_;
};

// An output could not be written (permissions, full disk); what was published stays valid.
class IRMOSAIC_EXPORT OutputError : public Error {
 public:
  explicit OutputError(const std::string& message) : Error(message) {}
};

}  // namespace irmosaic
