// replay://FILE and SampleRecorder: the stream file, format v1 (docs/sources.md).
#include <fmt/format.h>
#include <pthread.h>

#include <algorithm>
#include <cerrno>
#include <charconv>
#include <chrono>
#include <cstring>
#include <limits>
#include <string>
#include <vector>

#include "core.hpp"
#include "mrskin/driver/errors.hpp"

namespace mrskin::bridge {
namespace {

constexpr std::string_view kFileMagic = "# mrskin-stream 1";
constexpr std::string_view kColumns =
    "# stamp_ns received_ns force_N indentation_m contact_x_m contact_y_m tip_radius_m";
constexpr std::size_t kMaxLine = 512;

struct FileCloser {
  void operator()(std::FILE* f) const noexcept {
    (void)std::fclose(f);  // NOLINT(cppcoreguidelines-owning-memory)
  }
};

// Splits a line into whitespace-separated fields; false when there are not exactly n.
template <std::size_t N>
bool split(std::string_view line, std::array<std::string_view, N>& fields) noexcept {
  std::size_t count = 0;
  std::size_t i = 0;
  while (i < line.size()) {
    while (i < line.size() && (line[i] == ' ' || line[i] == '\t')) {
      ++i;
    }
    if (i == line.size()) {
      break;
    }
    const std::size_t start = i;
    while (i < line.size() && line[i] != ' ' && line[i] != '\t') {
      ++i;
    }
    if (count == N) {
      return false;
    }
    fields[count++] = line.substr(start, i - start);
  }
  return count == N;
}

template <class T>
bool parse(std::string_view text, T& value) noexcept {
  const auto [end, ec] = std::from_chars(text.data(), text.data() + text.size(), value);
  return ec == std::errc{} && end == text.data() + text.size();
}

class ReplaySource final : public StreamSource {
 public:
  ReplaySource(const std::string& path, SourceOptions options) : options_(std::move(options)) {
    std::unique_ptr<std::FILE, FileCloser> file(std::fopen(path.c_str(), "r"));
    if (!file) {
      throw Error("replay source: cannot open '" + path + "': " + std::strerror(errno));
    }
    std::array<char, kMaxLine + 2> buffer{};
    bool first = true;
    std::size_t line_number = 0;
    sources::OrderGate gate(std::numeric_limits<std::uint32_t>::max());
    while (std::fgets(buffer.data(), static_cast<int>(buffer.size()), file.get()) != nullptr) {
      std::string_view line(buffer.data());
      ++line_number;
      if (!line.ends_with('\n') && std::feof(file.get()) == 0) {
        if (first) {
          throw Error("replay source: '" + path +
                      "' is not a mrskin stream file v1 (its first line must be '" + std::string(kFileMagic) +
                      "')");
        }
        // Skip the rest of the overlong line.
        sources::drop(stats_, events_, DropReason::oversized, [&] {
          return fmt::format("replay '{}': a line over {} characters skipped", path, kMaxLine);
        });
        int c = 0;
        while ((c = std::fgetc(file.get())) != EOF && c != '\n') {
        }
        first = false;
        continue;
      }
      while (!line.empty() && (line.back() == '\n' || line.back() == '\r')) {
        line.remove_suffix(1);
      }
      if (first) {
        first = false;
        if (line != kFileMagic) {
          throw Error("replay source: '" + path +
                      "' is not a mrskin stream file v1 (its first line must be '" + std::string(kFileMagic) +
                      "')");
        }
        continue;
      }
      if (line.empty() || line.starts_with('#')) {
        continue;
      }
      load_line(line, gate, line_number);
    }
    if (first) {
      throw Error("replay source: '" + path + "' is empty (expected '" + std::string(kFileMagic) + "')");
    }
    if (!entries_.empty()) {
      base_ = entries_.front().due;
      const Duration span = entries_.back().due - base_;
      const Duration period =
          entries_.size() > 1 ? span / static_cast<std::int64_t>(entries_.size() - 1) : Duration{0};
      cycle_ = span + std::max(period, Duration{std::chrono::milliseconds(1)});
    }
  }

  [[nodiscard]] SourceStats stats() const noexcept override { return stats_.snapshot(); }
  [[nodiscard]] std::vector<SourceEvent> events_after(std::uint64_t seq) const override {
    return events_.after(seq);
  }
  [[nodiscard]] std::uint64_t event_count() const noexcept override { return events_.count(); }
  [[nodiscard]] std::string last_warning() const override { return events_.last_warning(); }

  bool latest(TimePoint now, SlaveSample& out) noexcept override {
    if (entries_.empty()) {
      return false;
    }
    if (options_.replay_max_speed) {
      return next_as_fast_as_possible(now, out);
    }
    if (!started_) {
      started_ = true;
      start_ = now;
    }
    Duration elapsed = now - start_;
    if (elapsed < Duration{0}) {
      return false;
    }
    std::int64_t cycle = 0;
    if (options_.replay_loop) {
      cycle = elapsed / cycle_;
      elapsed = elapsed % cycle_;
    }
    // The last entry due at or before elapsed.
    const auto it = std::upper_bound(entries_.begin(), entries_.end(), base_ + elapsed,
                                     [](TimePoint t, const Entry& e) { return t < e.due; });
    const Entry* e = nullptr;
    if (it != entries_.begin()) {
      e = &*(it - 1);
    } else if (cycle > 0) {
      e = &entries_.back();  // the previous cycle's last sample
      --cycle;
    } else {
      return false;
    }
    const TimePoint origin = start_ + cycle * cycle_ - base_;
    out = e->sample;
    out.stamp = origin + e->sample.stamp;
    out.received = origin + e->due;
    out.valid = true;
    return true;
  }

 private:
  struct Entry {
    SlaveSample sample;  // stamp: as in the file
    TimePoint due{};     // its arrival: received_ns, never before the previous entry's
  };

  void load_line(std::string_view line, sources::OrderGate& gate, std::size_t number) {
    using sources::drop;
    std::array<std::string_view, 7> f;
    std::int64_t stamp_ns = 0;
    std::int64_t received_ns = 0;
    SlaveSample s;
    if (!split(line, f) || !parse(f[0], stamp_ns) || !parse(f[1], received_ns) || !parse(f[2], s.force_N) ||
        !parse(f[3], s.indentation_m) || !parse(f[4], s.contact_x_m) || !parse(f[5], s.contact_y_m) ||
        !parse(f[6], s.tip_radius_m)) {
      drop(stats_, events_, DropReason::format, [&] {
        return fmt::format(
            "replay line {} skipped: not 7 numbers (stamp_ns received_ns force_N indentation_m "
            "contact_x_m contact_y_m tip_radius_m)",
            number);
      });
      return;
    }
    if (!sources::values_ok(s, options_, stats_, events_)) {
      return;
    }
    if (!sources::stamp_ok(stamp_ns) || !sources::stamp_ok(received_ns)) {
      drop(stats_, events_, DropReason::stamp,
           [&] { return fmt::format("replay line {} skipped: a stamp outside 0..2^62 ns", number); });
      return;
    }
    switch (gate.check(stamp_ns)) {
      case sources::OrderGate::Verdict::duplicate:
        drop(stats_, events_, DropReason::duplicate, [&] {
          return fmt::format("replay line {} skipped: its stamp repeats the line before", number);
        });
        return;
      case sources::OrderGate::Verdict::out_of_order:
      case sources::OrderGate::Verdict::restart:
        drop(stats_, events_, DropReason::out_of_order, [&] {
          return fmt::format(
              "replay line {} skipped: its stamp is older than the line before (stamps must "
              "increase)",
              number);
        });
        return;
      case sources::OrderGate::Verdict::accept:
        break;
    }
    if (entries_.size() >= options_.max_replay_samples) {
      drop(stats_, events_, DropReason::oversized, [&] {
        return fmt::format("replay: samples past {} skipped (max_replay_samples)",
                           options_.max_replay_samples);
      });
      return;
    }
    s.stamp = TimePoint{stamp_ns};
    s.valid = true;
    TimePoint due{received_ns};
    if (!entries_.empty()) {
      due = std::max(due, entries_.back().due);
    }
    entries_.push_back(Entry{s, due});
    stats_.accepted.bump();
  }

  bool next_as_fast_as_possible(TimePoint now, SlaveSample& out) noexcept {
    if (next_ < entries_.size()) {
      last_ = entries_[next_].sample;
      last_.stamp = now;
      last_.received = now;
      ++next_;
      if (next_ == entries_.size() && options_.replay_loop) {
        next_ = 0;
      }
    }
    out = last_;
    return last_.valid;
  }

  SourceOptions options_;
  sources::AtomicStats stats_;
  sources::SourceEvents events_;
  std::vector<Entry> entries_;
  TimePoint base_{};
  Duration cycle_{};
  bool started_ = false;
  TimePoint start_{};
  std::size_t next_ = 0;
  SlaveSample last_{};
};

}  // namespace

namespace sources {
std::unique_ptr<StreamSource> open_replay(const std::string& path, const SourceOptions& options) {
  return std::make_unique<ReplaySource>(path, options);
}
}  // namespace sources

// ---- recorder --------------------------------------------------------------------------------

SampleRecorder::SampleRecorder(const std::string& path, std::size_t capacity)
    : queue_(capacity), file_(std::fopen(path.c_str(), "w")) {
  if (file_ == nullptr) {
    throw Error("sample recorder: cannot create '" + path + "': " + std::strerror(errno));
  }
  fmt::print(file_, "{}\n{}\n", kFileMagic, kColumns);
  writer_ = std::thread([this] {
    (void)::pthread_setname_np(::pthread_self(), "mrskin-record");
    run();
  });
}

SampleRecorder::~SampleRecorder() { close(); }

bool SampleRecorder::record(const SlaveSample& sample) noexcept {
  if (!sample.valid || (have_last_ && sample.stamp == last_stamp_)) {
    return false;
  }
  have_last_ = true;
  last_stamp_ = sample.stamp;
  if (!queue_.try_push(sample)) {
    dropped_.bump();
    return false;
  }
  return true;
}

void SampleRecorder::close() noexcept {
  if (!writer_.joinable()) {
    return;
  }
  stop_.store(true, std::memory_order_release);
  writer_.join();
  (void)std::fclose(file_);  // NOLINT(cppcoreguidelines-owning-memory)
  file_ = nullptr;
}

void SampleRecorder::run() noexcept {
  bool have_origin = false;
  TimePoint origin{};
  for (;;) {
    const bool stopping = stop_.load(std::memory_order_acquire);
    SlaveSample s;
    bool any = false;
    while (queue_.try_pop(s)) {
      any = true;
      if (!have_origin) {
        have_origin = true;
        origin = s.stamp;
      }
      const TimePoint received = s.received.count() != 0 ? s.received : s.stamp;
      try {
        fmt::print(file_, "{} {} {} {} {} {} {}\n", (s.stamp - origin).count(), (received - origin).count(),
                   s.force_N, s.indentation_m, s.contact_x_m, s.contact_y_m, s.tip_radius_m);
        written_.bump();
      } catch (...) {  // a full disk: count it, keep draining
        dropped_.bump();
      }
    }
    if (any) {
      (void)std::fflush(file_);
    }
    if (stopping) {
      return;  // drained after the stop was seen: nothing is left behind
    }
    std::this_thread::sleep_for(std::chrono::milliseconds(2));
  }
}

}  // namespace mrskin::bridge
