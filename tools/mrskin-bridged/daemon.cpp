#include "daemon.hpp"

#include <fmt/format.h>
#include <fmt/ranges.h>
#include <pthread.h>
#include <spdlog/spdlog.h>

#include <algorithm>
#include <array>
#include <chrono>
#include <cmath>
#include <mutex>
#include <thread>

#include "json_text.hpp"
#include "mrskin/driver/atomic_raise.hpp"
#include "mrskin/driver/bus_budget_check.hpp"
#include "mrskin/eval/bus_stats.hpp"
#include "mrskin/eval/truth_scorer.hpp"
#include "mrskin/sim/open_mock.hpp"

namespace mrskin::bridged {

using bridge::Bridge;
using ctl::json_escape;
using ctl::json_number;

namespace {
// A stream source's I/O thread, after it queued a sample: wake the loop for a tick now.
void wake_loop(void* waiter) noexcept { static_cast<bridge::Waiter*>(waiter)->notify(); }
}  // namespace

OpenedSource open_source(const Settings& s, Clock& clock, bridge::Waiter* wake) {
  OpenedSource o;
  if (s.source.rfind("scene://", 0) == 0) {
    std::unique_ptr<bridge::Scene> scene = bridge::make_scene(s.source, s.mapping);
    o.scene = scene.get();
    o.source = std::move(scene);
    return o;
  }
  // udp://, replay://, igtl://, igtl-listen:// (docs/sources.md); InvalidArgument names the rest.
  std::unique_ptr<bridge::StreamSource> stream = bridge::open_stream(s.source, source_options(s), &clock);
  if (wake != nullptr) {
    stream->set_arrival_hook(&wake_loop, wake);
  }
  o.stream = stream.get();
  o.source = std::move(stream);
  return o;
}

bool WatchedSource::latest(TimePoint now, bridge::SlaveSample& out) noexcept {
  const bool ok = inner_.latest(now, out);
  if (ok && out.valid && (!any_ || out.stamp != last_stamp_)) {
    any_ = true;
    last_stamp_ = out.stamp;
    last_fresh_ = now;
    if (recorder_ != nullptr) {
      (void)recorder_->record(out);  // wait-free; a full queue is counted by the recorder
    }
  }
  return ok;
}

Daemon::Daemon(Settings settings, MonotonicClock& clock)
    : settings_(std::move(settings)),
      clock_(clock),
      waiter_(std::make_unique<bridge::MonotonicWaiter>()),
      shown_(settings_) {
  // A bad source URI, or a bad finger scene, fails before the device opens.
  finger_scene_ = open_finger_scene(settings_);
  source_ = open_source(settings_, clock_, waiter_.get());
  if (!settings_.record.empty()) {
    recorder_ = std::make_unique<bridge::SampleRecorder>(settings_.record);
  }
  dev_ = open_device(settings_.device, clock_);
  mock_ = sim::mock_of(dev_);
  if (mock_) {
    truth_.emplace(*mock_);
    finger_.assign(mock_->layout().fluid_cell_count(), 0.0);
    true_N_.assign(mock_->layout().fluid_cell_count(), 0.0);
  }
  const DeviceInfo& info = dev_.session->info();
  rows_ = info.rows;
  cols_ = info.cols;
  max_current_A_ = info.max_current_A;
  grid_ = std::make_unique<GridSeqlock>(info.fluid_cells, info.valves, info.sensors);
  sensor_unit_ = info.sensor_unit;
  const model::DeviceProfile* profile = dev_.session->profile();
  force_range_N_ = profile != nullptr ? profile->design.force_range_N : 0.0;
  thermal_.reset(info.valves, profile != nullptr ? profile->coil.resistance_ohm : 0.0);
  t0_ = clock_.now();
  // The handshake and the configuration read are not the loop's traffic.
  reports_at_start_ = {dev_.session->counters().reports_sent, dev_.session->counters().reports_received};
  if (mock_ != nullptr) {
    bus_at_start_ = mock_->bus_stats();
    mock_->restart_bus_max_wait();
  }
  last_thermal_ = t0_;
  if (source_.scene != nullptr) {
    source_.scene->set_start(t0_);
  }
  if (finger_scene_) {
    finger_scene_->set_start(t0_);
  }
  finger_t0_ = t0_;
  finger_waits_ = finger_scene_ != nullptr && source_.stream != nullptr;
  if (!settings_.topics_namespace.empty()) {
    bridge::SkinTopicsOptions to;
    to.ns = settings_.topics_namespace;
    to.domain = settings_.topics_domain;
    topics_ = std::make_unique<bridge::SkinPublisher>(to);
  }
  fit_default_rate_to_bus();
  build_bridge(settings_);
  (void)bridge_->enable();
}

// Without a rate from the file or --rate, a bus that cannot carry the default 1000 Hz runs the
// loop at 80 % of the highest rate it carries, rounded down (docs/daemon.md); a rate
// that was asked for and does not fit is refused by the Bridge (BusOverloaded, exit 2), and so
// is a unit whose own telemetry overloads its bus (check_bus_budget throws even at 1 Hz).
void Daemon::fit_default_rate_to_bus() {
  default_rate_hz_ = Settings{}.rate_hz;
  if (settings_.rate_given) {
    return;
  }
  const DeviceInfo& info = dev_.session->info();
  const Transport& link = dev_.session->transport();
  BusBudgetCheck slowest;
  try {
    slowest = check_bus_budget(info, link, 1.0);
  } catch (const BusOverloaded&) {
    return;  // no rate fits: the Bridge refuses, naming the default rate and the buses that carry it
  }
  if (!slowest.limited || slowest.highest_rate_hz >= settings_.rate_hz) {
    return;
  }
  // 80 % of the highest: room for retries and bursts in the host's own traffic (the unit's
  // telemetry does not scale with the loop, so the bus may stay above 80 %: then it warns).
  const double rate_hz = std::floor(0.8 * slowest.highest_rate_hz);
  if (rate_hz < 1.0) {
    return;
  }
  rate_note_ = fmt::format(
      "rate: {} Hz does not fit {} for this unit (it carries {:.0f} Hz at most); the loop runs at {} Hz, "
      "80 % of that. Set rate_hz or --rate to choose (a rate that does not fit is refused)",
      settings_.rate_hz, protocol::to_string(slowest.bus.kind), std::floor(slowest.highest_rate_hz), rate_hz);
  default_rate_hz_ = rate_hz;
  settings_.rate_hz = rate_hz;
  shown_.rate_hz = rate_hz;
}

Daemon::~Daemon() {
  stop();
  loop_.reset();
  bridge_.reset();
  if (mock_) {
    mock_->stop();
  }
}

// On mock://, a scorer of the new bridge against the unit's truth (nullptr otherwise).
std::unique_ptr<eval::TruthScorer> Daemon::make_scorer(Bridge& b) {
  if (!truth_) {
    return nullptr;
  }
  auto scorer = std::make_unique<eval::TruthScorer>(*truth_, mock_->layout().fluid_cell_count(), b.options());
  b.set_tick_watcher(scorer.get());
  return scorer;
}

void Daemon::build_bridge(const Settings& s) {
  auto watched = std::make_unique<WatchedSource>(*source_.source, recorder_.get());
  auto b = std::make_unique<Bridge>(*dev_.session, *watched, bridge_options(s));
  std::unique_ptr<eval::TruthScorer> scorer = make_scorer(*b);
  bridge_ = std::move(b);  // the old bridge goes before the source wrapper it read, and its scorer
  scorer_ = std::move(scorer);
  watched_ = std::move(watched);
}

bridge::LoopOptions loop_options(const Settings& s, bridge::Waiter* waiter) {
  bridge::LoopOptions lo;
  lo.waiter = waiter;
  lo.rate_hz = s.rate_hz;
  lo.realtime = s.realtime;
  lo.priority = s.rt_priority;
  lo.cpu = s.cpu;
  return lo;
}

std::string Daemon::start() {
  if (!loop_) {
    loop_ = std::make_unique<bridge::RealtimeLoop>(clock_, *this, loop_options(settings_, waiter_.get()));
  }
  std::string warning = loop_->start();
  if (thread_cpu_t0_ == TimePoint{}) {
    thread_cpu_t0_ = clock_.now();
    thread_cpu_.sample();  // the baseline: the start-up's CPU time is not the run's
  }
  if (topics_ && !topics_thread_.joinable()) {
    {
      const std::lock_guard<std::mutex> lock(topics_mutex_);
      topics_stop_ = false;
    }
    topics_on_.store(true, std::memory_order_relaxed);
    topics_thread_ = std::thread([this] {
      (void)::pthread_setname_np(::pthread_self(), "mrskin-topics");
      publish_topics();
    });
  }
  if (warned_) {
    return {};  // a reload's new loop would repeat it
  }
  warned_ = !warning.empty();
  return warning;
}

void Daemon::stop() noexcept {
  if (topics_thread_.joinable()) {
    {
      const std::lock_guard<std::mutex> lock(topics_mutex_);
      topics_stop_ = true;
    }
    topics_wake_.notify_all();
    topics_thread_.join();
    topics_on_.store(false, std::memory_order_relaxed);
  }
  if (loop_) {
    loop_->stop();
  }
  if (recorder_) {
    recorder_->close();  // the tick no longer records: flush and close the file
  }
}

ResultCode Daemon::tick(TimePoint now) noexcept {
  if (!gate_.try_tick()) {
    return ResultCode::ok;  // the control thread holds the session (a fault dump, a lease)
  }
  if (const unsigned char r = pending_.exchange(0, std::memory_order_acq_rel); r != 0) {
    bridge_->request(static_cast<Bridge::Request>(r));
    operator_halt_.store(r == static_cast<unsigned char>(Bridge::Request::enable) ? 0 : r,
                         std::memory_order_relaxed);
  }
  const ResultCode rc = bridge_->step(now);
  bridge::SensorFaultEvent fault;
  while (bridge_->take_sensor_fault(fault)) {
    (void)sensor_faults_.try_push(fault);  // 64 behind: the bridge's count still has it
  }
  publish(now);
  gate_.end_tick();
  return rc;
}

void Daemon::publish(TimePoint now) noexcept {
  const DeviceSession& s = *dev_.session;
  const SessionCounters& c = s.counters();
  state_.store(static_cast<std::uint8_t>(s.state()), std::memory_order_relaxed);
  fault_code_.store(s.fault_code(), std::memory_order_relaxed);
  last_fault_code_.store(s.last_fault_code(), std::memory_order_relaxed);
  faults_.set(c.faults);
  halted_.store(bridge_->halted(), std::memory_order_relaxed);
  connected_.store(s.connected(), std::memory_order_relaxed);
  valves_released_.store(s.valves_released(), std::memory_order_relaxed);
  ticks_.set(bridge_->live_ticks());
  rms_N_.store(bridge_->live_rms_error_N(), std::memory_order_relaxed);
  stiffness_.store(bridge_->live_stiffness_N_per_m(), std::memory_order_relaxed);
  double peak_N = 0.0;
  for (const double f : bridge_->targets_N()) {
    peak_N = std::max(peak_N, f);
  }
  peak_target_N_.store(peak_N, std::memory_order_relaxed);
  double peak_A = 0.0;
  for (const double a : bridge_->currents_A()) {
    peak_A = std::max(peak_A, a);
  }
  peak_current_A_.store(peak_A, std::memory_order_relaxed);
  sent_.set(c.sent);
  received_.set(c.received);
  identity_changes_.set(c.identity_changes);
  crc_errors_.set(c.crc_errors);
  decode_errors_.set(c.decode_errors);
  sequence_gaps_.set(c.sequence_gaps);
  link_duplicates_.set(c.duplicates);
  telemetry_timeouts_.set(c.telemetry_timeouts);
  disconnects_.set(c.disconnects);
  reconnects_.set(c.reconnects);
  if (c.last_round_trip_ns > max_round_trip_ns_.load(std::memory_order_relaxed)) {
    max_round_trip_ns_.store(c.last_round_trip_ns, std::memory_order_relaxed);  // one writer: the tick
  }
  last_fresh_ns_.store(watched_->last_fresh().count(), std::memory_order_relaxed);
  if (s.connected()) {
    disconnected_since_ns_.store(0, std::memory_order_relaxed);
  } else if (disconnected_since_ns_.load(std::memory_order_relaxed) == 0) {
    disconnected_since_ns_.store(std::max<std::int64_t>(1, now.count()), std::memory_order_relaxed);
  }
  publish_grid(now);
}

void Daemon::publish_grid(TimePoint now) noexcept {
  if (now - last_thermal_ < kGridPeriod) {
    return;  // the arrays move slowly next to their readers: every 10 ms is plenty
  }
  const DeviceSession& s = *dev_.session;
  thermal_.step(s.commanded_currents(), s.valves_released(), to_seconds(now - last_thermal_));
  last_thermal_ = now;
  if (grid_subscribers_.load(std::memory_order_relaxed) == 0 && !topics_on_.load(std::memory_order_relaxed)) {
    return;
  }
  const model::CellObserver& observer = bridge_->observer();
  grid_->begin_write(now.count());
  grid_->write(GridSeqlock::force_n, observer.force_N());
  grid_->write(GridSeqlock::displacement_m, observer.indentation_m());
  grid_->write(GridSeqlock::target_n, bridge_->targets_N());
  grid_->write(GridSeqlock::current_a, s.commanded_currents());
  grid_->write(GridSeqlock::temperature_c, thermal_.temperature_C());
  grid_->write(GridSeqlock::sensor, s.sensors());
  if (truth_) {
    truth_->true_forces(true_N_);
  }
  grid_->write(GridSeqlock::true_n, truth_ ? std::span<const double>(true_N_) : std::span<const double>());
  grid_->write(GridSeqlock::law_n, bridge_->law_N());
  grid_->write(GridSeqlock::floor_n, bridge_->envelope_floor_N());
  grid_->write(GridSeqlock::ceiling_n, bridge_->envelope_ceiling_N());
  grid_->end_write();
}

namespace {

const char* crtk_state(std::uint8_t state) noexcept {
  switch (static_cast<DeviceState>(state)) {
    case DeviceState::enabled:
      return "ENABLED";
    case DeviceState::paused:
      return "PAUSED";
    case DeviceState::fault:
      return "FAULT";
    case DeviceState::disabled:
      break;
  }
  return "DISABLED";
}

}  // namespace

// The skin's ROS 2 topics at [topics] rate_hz, from what the tick published (never in the tick):
// the fluid cells' arrays spread over the rows x cols grid, NaN where no fluid cell is.
void Daemon::publish_topics() noexcept {
  try {
    const GridLayout layout(rows_, cols_);
    const std::size_t n = static_cast<std::size_t>(rows_) * static_cast<std::size_t>(cols_);
    std::array<std::vector<double>, 3> grid{std::vector<double>(n, NAN), std::vector<double>(n, NAN),
                                            std::vector<double>(n, NAN)};
    GridSeqlock::Copy copy;
    const auto period = std::chrono::duration_cast<std::chrono::steady_clock::duration>(
        std::chrono::duration<double>(1.0 / settings_.topics_rate_hz));
    auto next = std::chrono::steady_clock::now();
    std::unique_lock<std::mutex> lock(topics_mutex_);
    while (!topics_wake_.wait_until(lock, next, [this] { return topics_stop_; })) {
      next += period;
      if (!grid_->read(copy)) {
        continue;  // the tick has not published yet
      }
      constexpr std::array<GridSeqlock::Array, 3> kFrom{GridSeqlock::target_n, GridSeqlock::force_n,
                                                        GridSeqlock::true_n};
      for (std::size_t a = 0; a < grid.size(); ++a) {
        const std::vector<double>& values = copy.arrays.at(kFrom.at(a));
        for (std::size_t i = 0; i < layout.fluid_cells().size() && i < values.size(); ++i) {
          const GridCell c = layout.fluid_cells()[i];
          grid.at(a).at(static_cast<std::size_t>(c.row) * static_cast<std::size_t>(cols_) +
                        static_cast<std::size_t>(c.col)) = values[i];
        }
      }
      bridge::SkinFrame f;
      f.stamp_ns = std::chrono::duration_cast<std::chrono::nanoseconds>(
                       std::chrono::system_clock::now().time_since_epoch())
                       .count();
      f.state = crtk_state(state_.load(std::memory_order_relaxed));
      f.rows = rows_;
      f.cols = cols_;
      f.target_N = grid[0];
      f.estimated_N = grid[1];
      if (truth_) {
        f.true_N = grid[2];
      }
      (void)topics_->publish(f);
    }
  } catch (const std::exception& e) {
    spdlog::error("skin topics stopped: {}", e.what());
  }
}

void Daemon::grid_subscribers(std::size_t n) noexcept {
  grid_subscribers_.store(n, std::memory_order_relaxed);
}

std::string Daemon::grid_members() {
  std::string out = fmt::format(
      R"("fault":"{}","last_fault":"{}","faults":{},"valves_released":{},"connected":{},"rows":{},"cols":{},)"
      R"("max_current_a":{},"force_range_n":{},"sensor_unit":"{}",)",
      fault_name(fault_code_.load(std::memory_order_relaxed)),
      fault_name(last_fault_code_.load(std::memory_order_relaxed)), faults_.value(),
      valves_released_.load(std::memory_order_relaxed), connected_.load(std::memory_order_relaxed), rows_,
      cols_, json_number(max_current_A_), json_number(force_range_N_), sensor_unit_);
  const double hottest_C = mock_ ? mock_->max_coil_temperature_C() : NAN;
  out += fmt::format(R"("max_coil_temperature_c":{})", json_number(hottest_C));
  if (!grid_->read(grid_copy_)) {
    return out + R"(,"grid_t_s":null)";  // nothing published yet (the first 10 ms of a subscription)
  }
  out += fmt::format(R"(,"grid_t_s":{})",
                     json_number(static_cast<double>(grid_copy_.t_ns - t0_.count()) * 1e-9));
  static constexpr std::array<const char*, GridSeqlock::kArrays> kNames = {
      "force_n", "displacement_m", "target_n", "current_a", "temperature_c",
      "sensor",  "true_force_n",   "law_n",    "floor_n",   "ceiling_n"};
  for (std::size_t a = 0; a < GridSeqlock::kArrays; ++a) {
    out += fmt::format(R"(,"{}":[)", kNames.at(a));
    const std::vector<double>& values = grid_copy_.arrays.at(a);
    for (std::size_t i = 0; i < values.size(); ++i) {
      if (i != 0) {
        out += ',';
      }
      out += json_number(values[i]);
    }
    out += ']';
  }
  return out;
}

void Daemon::request(std::string_view cmd) {
  const Bridge::Request r = cmd == "estop"     ? Bridge::Request::estop
                            : cmd == "disable" ? Bridge::Request::disable
                                               : Bridge::Request::enable;
  atomic_raise(pending_, static_cast<unsigned char>(r));  // the strongest pending request wins
}

std::string Daemon::stream_state(std::int64_t now_ns) const {
  if (halted_.load(std::memory_order_relaxed)) {
    return "not read while halted";  // the bridge skips the source until enable
  }
  const std::int64_t last = last_fresh_ns_.load(std::memory_order_relaxed);
  if (last == 0) {
    return "no sample yet";
  }
  double hold_s = 0.0;
  double fade_s = 0.0;
  {
    const std::lock_guard<std::mutex> lock(shown_mutex_);
    hold_s = shown_.stale_hold_s;
    fade_s = shown_.stale_fade_s;
  }
  const double age_s = static_cast<double>(now_ns - last) * 1e-9;
  if (age_s <= std::max(hold_s, 0.01)) {
    return "live";
  }
  return age_s <= hold_s + fade_s ? "stale, fading" : "stale, released";
}

std::string Daemon::stream_warning() const {
  // The control thread asks too; a reload with a new source swaps source_ under this lock.
  const std::lock_guard<std::mutex> lock(shown_mutex_);
  return source_.stream != nullptr ? source_.stream->last_warning() : std::string{};
}

std::string Daemon::status_members() {
  Settings shown;
  std::string faulty;
  {
    const std::lock_guard<std::mutex> lock(shown_mutex_);
    shown = shown_;
    for (const auto& [sensor, fault] : faulty_sensors_) {
      faulty += fmt::format(R"({}{{"sensor":{},"fault":"{}"}})", faulty.empty() ? "" : ",", sensor,
                            bridge::to_string(fault));
    }
  }
  const std::int64_t now_ns = clock_.now().count();
  const auto state = static_cast<DeviceState>(state_.load(std::memory_order_relaxed));
  const unsigned char halt = operator_halt_.load(std::memory_order_relaxed);
  return fmt::format(
      R"("state":"{}","fault":"{}","last_fault":"{}","faults":{},"halted":{},"operator":"{})"
      R"(",)"
      R"("valves_released":{},"connected":{},"stream":"{}","ticks":{},"rms_error_n":{},)"
      R"("stiffness_n_per_m":{},"peak_target_n":{},"peak_current_a":{},"rate_hz":{},"device":"{}",)"
      R"("source":"{}","uptime_s":{},"link_sent":{},"link_received":{},"reloads":{},"pid":{},"leased":{},)"
      R"("stream_warning":"{}","topics":{},"link_errors":{{"sequence_gaps":{},"duplicates":{},)"
      R"("undecodable":{},"crc":{},"telemetry_timeouts":{},"disconnects":{},"reconnects":{}}},)"
      R"("sensor_faults":[{}])",
      to_string(state), fault_name(fault_code_.load(std::memory_order_relaxed)),
      fault_name(last_fault_code_.load(std::memory_order_relaxed)), faults_.value(),
      halted_.load(std::memory_order_relaxed),
      halt == 3   ? "estop"
      : halt == 2 ? "disable"
                  : "enable",
      valves_released_.load(std::memory_order_relaxed), connected_.load(std::memory_order_relaxed),
      stream_state(now_ns), ticks_base_.load() + ticks_.value(),
      json_number(rms_N_.load(std::memory_order_relaxed)),
      json_number(stiffness_.load(std::memory_order_relaxed)),
      json_number(peak_target_N_.load(std::memory_order_relaxed)),
      json_number(peak_current_A_.load(std::memory_order_relaxed)), json_number(shown.rate_hz),
      json_escape(shown.device), json_escape(shown.source),
      json_number(static_cast<double>(now_ns - t0_.count()) * 1e-9), sent_.value(), received_.value(),
      reloads_.load(), ::getpid(), leased_.load(), json_escape(stream_warning()), topics_members(),
      sequence_gaps_.value(), link_duplicates_.value(), decode_errors_.value(), crc_errors_.value(),
      telemetry_timeouts_.value(), disconnects_.value(), reconnects_.value(), faulty);
}

std::string Daemon::topics_members() const {
  if (!topics_) {
    return "null";
  }
  return fmt::format(R"({{"namespace":"{}","subscribers":{},"published":{},"failures":{}}})",
                     json_escape(topics_->ns()), topics_->subscribers(), topics_->published(),
                     topics_->failures());
}

std::string Daemon::telemetry_members() {
  const std::int64_t now_ns = clock_.now().count();
  return fmt::format(R"("t_s":{},"state":"{}","halted":{},"stream":"{}","ticks":{},"rms_error_n":{},)"
                     R"("stiffness_n_per_m":{},"peak_target_n":{},"peak_current_a":{})",
                     json_number(static_cast<double>(now_ns - t0_.count()) * 1e-9),
                     to_string(static_cast<DeviceState>(state_.load(std::memory_order_relaxed))),
                     halted_.load(std::memory_order_relaxed), stream_state(now_ns),
                     ticks_base_.load() + ticks_.value(), json_number(rms_N_.load()),
                     json_number(stiffness_.load()), json_number(peak_target_N_.load()),
                     json_number(peak_current_A_.load()));
}

std::string Daemon::lease_begin() {
  if (leased_.load()) {
    return "the device is already leased";
  }
  request("disable");  // the valves released and the device disabled by the bridge's own tick
  const auto give_up = std::chrono::steady_clock::now() + std::chrono::seconds(2);
  while (!halted_.load(std::memory_order_acquire) || pending_.load(std::memory_order_acquire) != 0) {
    if (std::chrono::steady_clock::now() > give_up) {
      return "the bridge did not halt within 2 s";
    }
    std::this_thread::sleep_for(std::chrono::milliseconds(1));
  }
  // The gate held until lease_end(): the tick skips its step meanwhile.
  if (!gate_.try_read(std::chrono::milliseconds(200))) {
    return "the tick did not yield; try again";
  }
  leased_.store(true);
  return {};
}

Transport* Daemon::leased_transport() noexcept {
  return leased_.load() ? &dev_.session->transport() : nullptr;
}

void Daemon::lease_end() noexcept {
  leased_.store(false);
  gate_.end_read();
}

std::string Daemon::fault_members() {
  // The gate: once in, the tick skips its step (at most a tick or two) until end_read().
  if (!gate_.try_read(std::chrono::milliseconds(200))) {
    return R"("error":"the tick did not yield; try again")";
  }
  const DeviceSession& s = *dev_.session;
  const DeviceState state = s.state();
  const std::uint8_t code = s.fault_code();
  const std::uint8_t last_code = s.last_fault_code();
  const std::uint64_t faults = s.counters().faults;
  const double fault_time_s = to_seconds(s.last_fault_time() - t0_);
  std::vector<LogEntry> entries;
  std::string text;
  std::exception_ptr failed;
  try {
    const std::vector<TrafficRecord> records = faults > 0 ? s.fault_log() : std::vector<TrafficRecord>{};
    entries = s.decode_log(records);
    text = s.format_log(records);
  } catch (...) {
    failed = std::current_exception();
  }
  gate_.end_read();
  if (failed) {
    return R"("error":"out of memory while copying the ring log")";
  }
  std::string out = fmt::format(R"("state":"{}","fault":"{}","faults":{},"last_fault":"{}")",
                                to_string(state), fault_name(code), faults, fault_name(last_code));
  if (faults == 0) {
    return out + R"(,"log":[])";
  }
  out += fmt::format(R"(,"last_fault_time_s":{},"log":[)", json_number(fault_time_s));
  std::size_t line_begin = 0;
  for (std::size_t i = 0; i < entries.size(); ++i) {
    const LogEntry& e = entries[i];
    const std::size_t line_end = std::min(text.find('\n', line_begin), text.size());
    const std::string_view line = std::string_view(text).substr(line_begin, line_end - line_begin);
    line_begin = line_end + 1;
    out += fmt::format(R"({}{{"t_s":{},"dir":"{}","kind":"{}","seq":{},"state":"{}","fault":"{}","text":)"
                       R"("{}"}})",
                       i == 0 ? "" : ",", json_number(to_seconds(e.host_time - t0_)), e.sent ? "tx" : "rx",
                       e.kind, e.sequence, e.state, e.fault, json_escape(line));
  }
  return out + "]";
}

std::unique_ptr<bridge::Scene> open_finger_scene(const Settings& s) {
  if (!s.device.starts_with("mock://")) {
    return nullptr;
  }
  const std::string name = sim::parse_mock_uri(s.device).options.finger_scene;
  return name.empty() ? nullptr : bridge::make_scene(name, s.mapping);
}

void Daemon::drive_finger() {
  bridge::Scene* script = finger_scene_ ? finger_scene_.get() : source_.scene;
  if (mock_ && script != nullptr) {
    // At the script's start until the stream's first sample (finger_waits_): see finger_t0_.
    finger_waits_ = finger_waits_ && source_.stream != nullptr && source_.stream->stats().accepted == 0;
    finger_t0_ = finger_waits_ ? clock_.now() : finger_t0_;
    mrskin::eval::press_scene_finger(*script, to_seconds(clock_.now() - finger_t0_), mock_->layout(), finger_,
                                     bridge_->scale().length);
    mock_->set_finger_indentation(finger_);
  }
}

std::vector<bridge::SourceEvent> Daemon::take_source_events() {
  if (source_.stream == nullptr || source_.stream->event_count() == events_seen_) {
    return {};
  }
  std::vector<bridge::SourceEvent> events = source_.stream->events_after(events_seen_);
  if (!events.empty()) {
    events_seen_ = events.back().seq;
  }
  return events;
}

std::vector<Daemon::HealthEvent> Daemon::take_health_events() {
  std::vector<HealthEvent> out;
  const TimePoint now = clock_.now();
  const std::array<std::uint64_t, 7> link{
      crc_errors_.value(),         decode_errors_.value(), sequence_gaps_.value(), link_duplicates_.value(),
      telemetry_timeouts_.value(), disconnects_.value(),   reconnects_.value()};
  const double period_s = seen_.at.count() == 0 ? to_seconds(now - t0_) : to_seconds(now - seen_.at);
  std::array<std::uint64_t, 7> d{};
  for (std::size_t k = 0; k < d.size(); ++k) {
    d.at(k) = link.at(k) - seen_.link.at(k);
  }
  // decode_errors counts every undecodable packet, CRC failures included.
  std::string errors;
  const auto add = [&](std::uint64_t n, std::string_view what) {
    if (n != 0) {
      errors += fmt::format("{}{} {}", errors.empty() ? "" : ", ", n, what);
    }
  };
  add(d[2], "sequence gaps (telemetry lost or reordered)");
  add(d[3], "duplicate packets");
  add(d[1], d[0] != 0 ? fmt::format("undecodable packets ({} failed the CRC)", d[0]) : "undecodable packets");
  add(d[4], "telemetry timeouts (nothing heard in time)");
  if (!errors.empty()) {
    out.push_back({true, fmt::format("link: in the last {:.1f} s: {} (totals: {} gaps, {} duplicates, {} "
                                     "undecodable, {} timeouts)",
                                     period_s, errors, link[2], link[3], link[1], link[4])});
  }
  // Late data: every packet arrives, but late (a loaded bus or host); the sensors the loop closes
  // on are that old. Full-speed USB and CAN answer within a few ms.
  constexpr std::int64_t kLateRoundTrip_ns = 20'000'000;
  if (const std::int64_t rtt_ns = max_round_trip_ns_.exchange(0); rtt_ns > kLateRoundTrip_ns) {
    out.push_back(
        {true, fmt::format("link: heartbeat round trip up to {:.0f} ms in the last {:.1f} s (over {} ms): "
                           "the device's data arrives that late",
                           static_cast<double>(rtt_ns) * 1e-6, period_s, kLateRoundTrip_ns / 1'000'000)});
  }
  if (d[5] != 0) {
    out.push_back(
        {true, fmt::format("link: the device disconnected (disconnects so far: {}); the session reconnects",
                           link[5])});
  }
  if (d[6] != 0) {
    out.push_back({false, fmt::format("link: the device reconnected (reconnects so far: {})", link[6])});
  }
  const std::uint8_t state = state_.load(std::memory_order_relaxed);
  const std::uint8_t fault = fault_code_.load(std::memory_order_relaxed);
  const auto fault_state = static_cast<std::uint8_t>(DeviceState::fault);
  if (state == fault_state && (seen_.state != fault_state || fault != seen_.fault)) {
    const bool asked = operator_halt_.load(std::memory_order_relaxed) == 3;
    out.push_back({!asked, fmt::format("device FAULT: {}{} (faults so far: {})", fault_name(fault),
                                       asked ? ", as the operator asked" : "", faults_.value())});
  } else if (state != fault_state && seen_.state == fault_state) {
    out.push_back({false, fmt::format("device left FAULT: {}", to_string(static_cast<DeviceState>(state)))});
  }
  const std::int64_t last = last_fresh_ns_.load(std::memory_order_relaxed);
  if (last != 0 && !halted_.load(std::memory_order_relaxed)) {
    const std::string stream = stream_state(now.count());
    const bool stale = stream != "live";
    if (stale && !seen_.stale) {
      out.push_back(
          {true, fmt::format("stream: no fresh sample for {:.2f} s ({}): the bridge holds, then fades "
                             "to released",
                             static_cast<double>(now.count() - last) * 1e-9, stream)});
    } else if (!stale && seen_.stale) {
      out.push_back({false, "stream: live again"});
    }
    seen_.stale = stale;
  }
  bridge::SensorFaultEvent e;
  while (sensor_faults_.try_pop(e)) {
    out.push_back({true, sensor_fault_text(e)});
    const std::lock_guard<std::mutex> lock(shown_mutex_);
    faulty_sensors_.emplace_back(e.sensor, e.fault);
  }
  seen_.link = link;
  seen_.state = state;
  seen_.fault = fault;
  seen_.at = now;
  return out;
}

std::string Daemon::sensor_fault_text(const bridge::SensorFaultEvent& e) const {
  const model::DeviceProfile* profile = dev_.session->profile();
  std::string where;
  if (profile != nullptr && e.sensor < profile->sensors.size()) {
    const model::SensorSpec& spec = profile->sensors[e.sensor];
    where = fmt::format(" (under {} {}", spec.place == model::PlaceKind::valve ? "valve" : "fluid cell",
                        spec.index);
    const std::span<const std::size_t> cells = bridge_->sensor_fault_monitor().cells_of_sensor(e.sensor);
    where += fmt::format(", reads fluid cell{} {})", cells.size() == 1 ? "" : "s", fmt::join(cells, ", "));
  }
  std::string what;
  switch (e.fault) {
    case bridge::SensorFault::stuck:
      what = fmt::format("stuck: the same reading ({:.1f} um) over and over", e.evidence * 1e6);
      break;
    case bridge::SensorFault::noisy:
      what = fmt::format("noisy: {:.1f} times the profile's noise", std::sqrt(std::max(e.evidence, 0.0)));
      break;
    case bridge::SensorFault::offset:
      what = fmt::format("offset: reads {:.0f} standard deviations {} what the other sensors explain",
                         std::abs(e.evidence), e.evidence > 0.0 ? "above" : "below");
      break;
    case bridge::SensorFault::none:
      what = "faulty";
      break;
  }
  std::string then;
  if (e.unobservable_cell != bridge::SensorFaultMonitor::npos) {
    then = fmt::format(
        "fluid cell {} is read by no healthy sensor now: valves released and the device disabled; enable "
        "is refused until the sensor is repaired and mrskin-bridged restarted",
        e.unobservable_cell);
  } else {
    then = fmt::format("left out of the observer; the {} sensors left read every cell, rendering goes on",
                       e.healthy_left);
  }
  return fmt::format("sensor {}{} {} at t={:.3f} s: {}", e.sensor, where, what, e.at_s, then);
}

std::string Daemon::status_line() const {
  const std::int64_t now_ns = clock_.now().count();
  const auto state = static_cast<DeviceState>(state_.load(std::memory_order_relaxed));
  std::string line = fmt::format(
      "t={:6.2f} s  ticks={:<7} state={:<8} stiffness={:6.1f} N/m  peak target={:5.3f} N  rms error={:6.4f} "
      "N",
      static_cast<double>(now_ns - t0_.count()) * 1e-9, ticks_base_.load() + ticks_.value(), to_string(state),
      stiffness_.load(), peak_target_N_.load(), rms_N_.load());
  if (state == DeviceState::fault) {
    line += fmt::format("  fault: {}", fault_name(fault_code_.load()));
  }
  if (halted_.load()) {
    line += "  halted";
  }
  if (const std::string stream = stream_state(now_ns); stream != "live") {
    line += "  stream " + stream;
    if (const std::string why = stream_warning(); !why.empty()) {
      line += " (" + why + ")";
    }
  }
  if (!connected_.load()) {
    line += "  device disconnected";
  }
  const std::lock_guard<std::mutex> lock(shown_mutex_);
  for (const auto& [sensor, fault] : faulty_sensors_) {
    line += fmt::format("  sensor {} {}", sensor, bridge::to_string(fault));
  }
  return line;
}

bool Daemon::device_lost(double for_s) const noexcept {
  if (identity_changes_.value() > 0) {
    return true;  // another unit answered: this session cannot carry on
  }
  const std::int64_t since = disconnected_since_ns_.load(std::memory_order_relaxed);
  return since != 0 && static_cast<double>(clock_.now().count() - since) * 1e-9 > for_s;
}

bool Daemon::unrequested_fault() const noexcept {
  return static_cast<DeviceState>(state_.load()) == DeviceState::fault &&
         operator_halt_.load() != static_cast<unsigned char>(Bridge::Request::estop);
}

Daemon::ReportsPerFrame Daemon::reports_per_frame() const noexcept {
  const double frames = std::max(1e-9, uptime_s()) * 1000.0;
  const SessionCounters& link = dev_.session->counters();
  return {static_cast<double>(link.reports_sent - reports_at_start_.first) / frames,
          static_cast<double>(link.reports_received - reports_at_start_.second) / frames};
}

void Daemon::sample_threads() {
  if (thread_cpu_t0_ != TimePoint{}) {
    thread_cpu_.sample();
  }
}

bridge::BridgeStats Daemon::final_stats() const {
  bridge::BridgeStats stats = bridge_->stats();
  stats.threads = thread_cpu_.totals();
  stats.threads_wall_s = thread_cpu_t0_ == TimePoint{} ? 0.0 : to_seconds(clock_.now() - thread_cpu_t0_);
  if (loop_) {
    stats.skipped_periods += loop_->stats().skipped_periods;
  }
  const SessionCounters& link = dev_.session->counters();
  // Busier direction, counted: reports (datagrams: protocol 1.2 packs several packets in one) per
  // 1 ms full-speed USB-HID frame, which carries one (docs/protocol.md, "Bus budget").
  const ReportsPerFrame counted = reports_per_frame();
  stats.bus_load = std::max(counted.host_to_device, counted.device_to_host);
  if (mock_ != nullptr) {
    // Measured on the bus model since the loop started: the `bus` object and bus_load.
    eval::fill_bus_stats(*mock_, stats, bus_at_start_);
  }
  stats.link = {link.sequence_gaps,      link.duplicates,  link.decode_errors, link.crc_errors,
                link.telemetry_timeouts, link.disconnects, link.reconnects};
  stats.device_faults = link.faults;
  if (source_.stream != nullptr) {
    const bridge::SourceStats in = source_.stream->stats();
    stats.samples_accepted = in.accepted;
    stats.samples_dropped = in.dropped();
    stats.samples_dropped_by_reason = in.drops;
    stats.stream_connections = in.connections;
    stats.stream_disconnects = in.disconnects;
    stats.stream_restarts = in.restarts;
  } else {
    stats.samples_accepted = stats.slave_samples;  // a scene's samples are all well-formed
  }
  return stats;
}

}  // namespace mrskin::bridged
