// The asynchronous data loader's core (train.workers, DESIGN.md section 8): `workers` threads
// make items 0, 1, 2, ... of a sequence with make(i) into a bounded window ahead of the consumer,
// which takes them in order. make(i) must depend on i alone (the trainer's samples draw their
// randomness from (seed, epoch, sample index)), so what the consumer gets is the same for any
// number of workers; with 0 workers take(i) calls make(i) itself and take_batch makes its items
// in parallel on the calling thread's OpenMP threads (the synchronous path).
//
// An exception thrown by make(i) is rethrown by take(i) (the other workers stop at their next
// item), so a bad scan stops training with its own message. The destructor stops and joins the
// workers; items made but not taken are dropped.
#pragma once

#include <condition_variable>
#include <cstddef>
#include <cstdint>
#include <exception>
#include <functional>
#include <map>
#include <mutex>
#include <optional>
#include <thread>
#include <vector>

#include "core/error.hpp"
#include "core/parallel.hpp"

namespace pillarseg {

template <class T>
class Prefetcher {
 public:
  // Items [0, count); at most `ahead` (>= 1) made and not yet taken.
  Prefetcher(std::size_t count, int workers, std::size_t ahead, std::function<T(std::size_t)> make)
      : count_(count), ahead_(ahead < 1 ? 1 : ahead), make_(std::move(make)) {
    PS_CHECK(workers >= 0, "train.workers must be >= 0, got {}", workers);
    for (int w = 0; w < workers; ++w) threads_.emplace_back([this] { work(); });
  }
  ~Prefetcher() {
    {
      std::lock_guard<std::mutex> lock(mutex_);
      stop_ = true;
    }
    changed_.notify_all();
    for (std::thread& t : threads_) t.join();
  }
  Prefetcher(const Prefetcher&) = delete;
  Prefetcher& operator=(const Prefetcher&) = delete;

  // Items [begin, begin + count), taken in order.
  std::vector<T> take_batch(std::size_t begin, std::size_t count) {
    std::vector<T> items(count);
    if (!threads_.empty()) {
      for (std::size_t k = 0; k < count; ++k) items[k] = take(begin + k);
      return items;
    }
    PS_CHECK(begin == next_take_ && begin + count <= count_,
             "Prefetcher: items [{}, {}) taken out of order (next is {} of {})", begin,
             begin + count, next_take_, count_);
    parallel_for(static_cast<std::int64_t>(count), [&](std::int64_t k) {
      items[static_cast<std::size_t>(k)] = make_(begin + static_cast<std::size_t>(k));
    });
    next_take_ += count;
    return items;
  }

  // Item i; items must be taken in order 0, 1, 2, ...
  T take(std::size_t i) {
    PS_CHECK(i == next_take_ && i < count_,
             "Prefetcher: item {} taken out of order (next is {} of {})", i, next_take_, count_);
    if (threads_.empty()) {
      ++next_take_;
      return make_(i);
    }
    std::unique_lock<std::mutex> lock(mutex_);
    changed_.wait(lock, [&] { return ready_.count(i) > 0 || failed_.count(i) > 0; });
    if (auto f = failed_.find(i); f != failed_.end()) std::rethrow_exception(f->second);
    T item = std::move(ready_.at(i));
    ready_.erase(i);
    ++next_take_;
    lock.unlock();
    changed_.notify_all();
    return item;
  }

 private:
  void work() {
    for (;;) {
      std::size_t i = 0;
      {
        std::unique_lock<std::mutex> lock(mutex_);
        changed_.wait(lock, [&] {
          return stop_ || next_make_ >= count_ || next_make_ < next_take_ + ahead_;
        });
        if (stop_ || next_make_ >= count_) return;
        i = next_make_++;
      }
      std::optional<T> item;
      std::exception_ptr error;
      try {
        item.emplace(make_(i));
      } catch (...) {
        error = std::current_exception();
      }
      {
        std::lock_guard<std::mutex> lock(mutex_);
        if (error) {
          failed_[i] = error;
          stop_ = true;  // the others stop at their next item
        } else {
          ready_.emplace(i, std::move(*item));
        }
      }
      changed_.notify_all();
    }
  }

  const std::size_t count_, ahead_;
  std::function<T(std::size_t)> make_;
  std::mutex mutex_;
  std::condition_variable changed_;
  std::map<std::size_t, T> ready_;
  std::map<std::size_t, std::exception_ptr> failed_;
  std::size_t next_make_ = 0, next_take_ = 0;
  bool stop_ = false;
  std::vector<std::thread> threads_;
};

}  // namespace pillarseg
