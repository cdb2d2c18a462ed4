#pragma once
// Private helper (src/map_fusion.cc): a fixed set of threads that help the calling thread with
// a batch of work, started once and kept for the object's life. A thread started per batch
// (std::async per frame) costs a thread creation per frame and, worse for an hour of flight,
// leaves memory behind with every thread that ran OpenCV: its per-thread data (cv::parallel_for_
// and cv::pyrDown keep some) grew the heap by ~0.7 KiB per frame (docs/benchmarks.md,
// "Session 18"). Not installed.
#include <pthread.h>

#include <condition_variable>
#include <cstddef>
#include <cstdint>
#include <exception>
#include <functional>
#include <mutex>
#include <string>
#include <thread>
#include <vector>

namespace irmosaic {

class HelperThreads {
 public:
  // Starts `count` threads named `name` (at most 15 characters are kept), idle until Run.
  HelperThreads(size_t count, const std::string& name) {
    threads_.reserve(count);
    for (size_t k = 0; k < count; ++k) {
      threads_.emplace_back([this, k, name] {
        pthread_setname_np(pthread_self(), name.substr(0, 15).c_str());
        Loop(k);
      });
    }
  }
  ~HelperThreads() {
    {
      std::lock_guard<std::mutex> lock(mu_);
      stop_ = true;
    }
    start_.notify_all();
    for (std::thread& t : threads_) t.join();
  }
  HelperThreads(const HelperThreads&) = delete;
  HelperThreads& operator=(const HelperThreads&) = delete;

  size_t size() const { return threads_.size(); }

  // Runs `work` on the calling thread and on `helpers` of the threads (at most size()) at once
  // and returns when every one of them has returned from it. The first exception thrown by any
  // of them is rethrown here, after all have finished. Not reentrant: one Run at a time.
  void Run(size_t helpers, const std::function<void()>& work) {
    helpers = std::min(helpers, threads_.size());
    {
      std::lock_guard<std::mutex> lock(mu_);
      work_ = &work;
      active_ = helpers;
      pending_ = helpers;
      failure_ = nullptr;
      ++batch_;
    }
    if (helpers > 0) start_.notify_all();
    std::exception_ptr failure;
    try {
      work();
    } catch (...) {
      failure = std::current_exception();
    }
    std::unique_lock<std::mutex> lock(mu_);
    done_.wait(lock, [this] { return pending_ == 0; });
    work_ = nullptr;
    if (!failure) failure = failure_;
    failure_ = nullptr;
    lock.unlock();
    if (failure) std::rethrow_exception(failure);
  }

 private:
  void Loop(size_t index) {
    uint64_t seen = 0;
    std::unique_lock<std::mutex> lock(mu_);
    while (true) {
      start_.wait(lock, [&] { return stop_ || batch_ != seen; });
      if (stop_) return;
      seen = batch_;
      if (index >= active_) continue;  // Not needed for this batch.
      const std::function<void()>* work = work_;
      lock.unlock();
      std::exception_ptr failure;
      try {
        (*work)();
      } catch (...) {
        failure = std::current_exception();
      }
      lock.lock();
      if (failure && !failure_) failure_ = failure;
      if (--pending_ == 0) done_.notify_all();
    }
  }

  std::mutex mu_;
  std::condition_variable start_, done_;
  const std::function<void()>* work_ = nullptr;
  size_t active_ = 0, pending_ = 0;
  uint64_t batch_ = 0;
  bool stop_ = false;
  std::exception_ptr failure_;
  std::vector<std::thread> threads_;  // Last: started after the state above exists.
};

}  // namespace irmosaic
