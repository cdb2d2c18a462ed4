#pragma once
// Private helper (src/map_fusion.cc, src/tile_store.cc): background threads (the optimizer,
// the store's writer) lower their own scheduling priority so that the threads placing new
// frames get the CPU first on a busy machine. Not installed.
#include <sys/resource.h>
#include <sys/syscall.h>
#include <unistd.h>

#include <algorithm>
#include <cerrno>

namespace irmosaic {

// Adds `increment` (clamped to nice 19) to the calling thread's nice value; Linux applies a
// thread id's nice value to that thread alone. 0 or less: nothing. Best effort: a refusal
// leaves the priority as it was.
inline void LowerThisThreadPriority(int increment) {
  if (increment <= 0) return;
  const int tid = static_cast<int>(::syscall(SYS_gettid));
  errno = 0;
  const int current = ::getpriority(PRIO_PROCESS, tid);
  if (errno == 0) ::setpriority(PRIO_PROCESS, tid, std::min(19, current + increment));
}

}  // namespace irmosaic
