// mrskin.bridge: a scene or a stream through the whole bridge, on the simulated clock (as the
// C++ tests run it: deterministic) or in real time (the library's loop thread). A Python callback
// gets every `decimation`-th rendered tick from TickRecorder, on the calling thread, never inside
// the tick. Statistics: bridge::to_json, as a dict.
#include "mrskin/bridge/bridge.hpp"

#include <pybind11/numpy.h>
#include <pybind11/stl.h>

#include <atomic>
#include <chrono>
#include <cmath>
#include <memory>
#include <optional>
#include <string>
#include <thread>
#include <vector>

#include "bindings.hpp"
#include "mrskin/bridge/scene.hpp"
#include "mrskin/bridge/sources.hpp"
#include "mrskin/bridge/stats.hpp"
#include "mrskin/driver/device.hpp"
#include "mrskin/eval/bus_stats.hpp"
#include "mrskin/eval/truth_scorer.hpp"
#include "mrskin/sim/open_mock.hpp"
#include "recorder.hpp"

namespace mrskin::python {

namespace {

using namespace std::chrono_literals;

constexpr std::size_t kRecorderSlots = 1024;

struct RunOptions {
  std::string source = "demo";
  std::string device = "mock://";
  double duration_s = 5.0;
  bridge::BridgeOptions bridge{};
  py::object callback = py::none();
  std::uint64_t decimation = 10;
};

bool is_scene(const std::string& source) {
  return source.find("://") == std::string::npos || source.starts_with("scene://");
}

// One tick handed to the callback.
struct TickSample {
  double t_s = 0.0;
  py::array_t<double> target_N;
  py::array_t<double> observed_force_N;
  py::object true_force_N = py::none();
};

py::array_t<double> to_array(std::span<const double> v) {
  return py::array_t<double>(static_cast<py::ssize_t>(v.size()), v.data());
}

// Everything a run needs, torn down in the right order by its destructor (also on Ctrl-C).
class Rig {
 public:
  Rig(const RunOptions& o, Clock& clock, bool synchronous) : clock_(clock) {
    // A bad source or scene raises before the device opens.
    if (is_scene(o.source)) {
      auto scene = bridge::make_scene(o.source);
      finger_ = scene.get();
      source_ = std::move(scene);
    } else {
      source_ = bridge::make_source(o.source, {}, &clock);
      stream_ = dynamic_cast<const bridge::StreamSource*>(source_.get());
    }
    OpenOptions open;
    open.synchronous_mock = synchronous;
    dev_ = open_device(o.device, clock, open);
    mock_ = sim::mock_of(dev_);
    if (mock_ && finger_ == nullptr) {
      const std::string finger = sim::parse_mock_uri(o.device).options.finger_scene;
      if (!finger.empty()) {
        finger_scene_ = bridge::make_scene(finger);
        finger_ = finger_scene_.get();
      }
    }
    bridge_ = std::make_unique<bridge::Bridge>(*dev_.session, *source_, o.bridge);
    if (mock_) {
      truth_.emplace(*mock_);
      cells_ = mock_->layout().fluid_cell_count();
      scorer_ = std::make_unique<eval::TruthScorer>(*truth_, cells_, bridge_->options());
    } else {
      cells_ = dev_.session->info().fluid_cells;
    }
    const ForceTruth* truth = truth_ ? &*truth_ : nullptr;
    recorder_ = std::make_unique<TickRecorder>(scorer_.get(), truth, cells_, o.decimation, kRecorderSlots);
    bridge_->set_tick_watcher(o.callback.is_none() ? static_cast<bridge::TickWatcher*>(scorer_.get())
                                                   : recorder_.get());
    finger_depth_m_.assign(cells_, 0.0);
    t0_ = clock.now();
    if (auto* scene = dynamic_cast<bridge::Scene*>(source_.get())) {
      scene->set_start(t0_);
    }
    if (finger_scene_) {
      finger_scene_->set_start(t0_);
    }
    finger_t0_ = t0_;
    // Beside a stream the mock's finger waits at its scene's start for the stream's first sample,
    // as mrskin-bridged's does (docs/daemon.md): a robot that plays the same scene starts late.
    finger_waits_ = finger_scene_ != nullptr && stream_ != nullptr;
  }
  Rig(const Rig&) = delete;
  Rig& operator=(const Rig&) = delete;
  Rig(Rig&&) = delete;
  Rig& operator=(Rig&&) = delete;
  ~Rig() {
    stop_finger_.store(true);
    if (finger_thread_.joinable()) {
      finger_thread_.join();
    }
    if (bridge_) {
      bridge_->stop();
    }
    bridge_.reset();
    if (mock_) {
      mock_->stop();
    }
  }

  // The simulated finger follows the script (the scene, or the mock's finger= scene). One thread
  // at a time calls it: the run's, or the finger thread of a real-time run.
  void press_finger() noexcept {
    if (mock_ && finger_ != nullptr) {
      // A replay:// file counts its samples as it loads them, so it never waits.
      finger_waits_ = finger_waits_ && stream_->stats().accepted == 0;
      finger_t0_ = finger_waits_ ? clock_.now() : finger_t0_;
      eval::press_scene_finger(*finger_, to_seconds(clock_.now() - finger_t0_), mock_->layout(),
                               finger_depth_m_, bridge_->scale().length);
      mock_->set_finger_indentation(finger_depth_m_);
    }
  }
  void start_finger_thread() {
    finger_thread_ = std::thread([this] {
      while (!stop_finger_.load(std::memory_order_relaxed)) {
        press_finger();
        std::this_thread::sleep_for(1ms);  // the script at ~1 kHz, as mrskin-bridged moves it
      }
    });
  }

  // Hands every recorded tick to the callback (GIL held).
  void drain(const py::object& callback) {
    std::uint32_t slot = 0;
    while (recorder_->take(slot)) {
      const TickRecorder::Sample s = recorder_->sample(slot);
      TickSample out;
      out.t_s = s.t_s;
      out.target_N = to_array(s.target_N);
      out.observed_force_N = to_array(s.observed_force_N);
      if (recorder_->has_truth()) {
        out.true_force_N = to_array(s.true_force_N);
      }
      recorder_->give_back(slot);
      callback(out);
    }
  }

  py::dict stats(bool with_callback) const {
    const py::module_ json = py::module_::import("json");
    bridge::BridgeStats st = bridge_->stats();
    if (mock_) {
      eval::fill_bus_stats(*mock_, st);  // the bus object and bus_load, as the C++ runs fill them
    }
    // A stream's own counters, as mrskin-bridged reports them (a scene has none of its own).
    if (const auto* stream = dynamic_cast<const bridge::StreamSource*>(source_.get()); stream != nullptr) {
      const bridge::SourceStats in = stream->stats();
      st.samples_accepted = in.accepted;
      st.samples_dropped = in.dropped();
      st.samples_dropped_by_reason = in.drops;
      st.stream_connections = in.connections;
      st.stream_disconnects = in.disconnects;
      st.stream_restarts = in.restarts;
    }
    py::dict d = json.attr("loads")(bridge::to_json(st, bridge_->tick_period_s()));
    if (with_callback) {
      d["callback_samples"] = recorder_->recorded();
      d["callback_dropped"] = recorder_->dropped();
    }
    return d;
  }

  [[nodiscard]] bridge::Bridge& bridge() noexcept { return *bridge_; }
  [[nodiscard]] sim::MockDevice* mock() const noexcept { return mock_.get(); }
  [[nodiscard]] TickRecorder& recorder() noexcept { return *recorder_; }

 private:
  Clock& clock_;
  std::unique_ptr<bridge::SlaveSource> source_;
  const bridge::StreamSource* stream_ = nullptr;  // source_ when it is a stream
  std::unique_ptr<bridge::Scene> finger_scene_;
  const bridge::Scene* finger_ = nullptr;
  OpenedDevice dev_;
  std::shared_ptr<sim::MockDevice> mock_;
  std::unique_ptr<bridge::Bridge> bridge_;
  std::optional<sim::MockDeviceTruth> truth_;
  std::unique_ptr<eval::TruthScorer> scorer_;
  std::unique_ptr<TickRecorder> recorder_;
  std::size_t cells_ = 0;
  std::vector<double> finger_depth_m_;
  TimePoint t0_{};
  TimePoint finger_t0_{};      // the finger's scene time 0: t0_, or the stream's first sample
  bool finger_waits_ = false;  // beside a stream, until its first accepted sample
  std::atomic<bool> stop_finger_{false};
  std::thread finger_thread_;
};

// The C++ tests' closed loop (tests/bridge/scene_rig.hpp): finger, device, tick, then the clock.
py::dict run_simulated(const RunOptions& o) {
  if (!o.device.starts_with("mock://")) {
    throw InvalidArgument("run_simulated needs a simulated unit (mock://...), not '" + o.device +
                          "': run_realtime drives hardware");
  }
  SimulatedClock clock;
  std::optional<Rig> rig;
  {
    const py::gil_scoped_release release;
    rig.emplace(o, clock, true);
    rig->bridge().set_perf_clock(&clock);  // no wall time anywhere: deterministic
    check_result(rig->bridge().enable(), "enable");
  }
  const Duration period = from_seconds(1.0 / o.bridge.rate_hz);
  const std::int64_t ticks = std::llround(o.duration_s * o.bridge.rate_hz);
  std::int64_t k = 0;
  while (k < ticks) {
    {
      const py::gil_scoped_release release;
      // Up to half the recorder's slots between drains: none is ever dropped here.
      const auto batch = static_cast<std::int64_t>(kRecorderSlots / 2 * o.decimation);
      for (const std::int64_t end = std::min(ticks, k + batch); k < end; ++k) {
        rig->press_finger();
        rig->mock()->step(clock.now());
        (void)rig->bridge().step(clock.now());
        clock.advance(period);
      }
    }
    if (PyErr_CheckSignals() != 0) {
      throw py::error_already_set();
    }
    if (!o.callback.is_none()) {
      rig->drain(o.callback);
    }
  }
  return rig->stats(!o.callback.is_none());
}

py::dict run_realtime(const RunOptions& o) {
  MonotonicClock clock;
  std::optional<Rig> rig;
  std::string warning;
  {
    const py::gil_scoped_release release;
    rig.emplace(o, clock, false);
    check_result(rig->bridge().enable(), "enable");
    rig->start_finger_thread();
    warning = rig->bridge().start(clock);
  }
  if (!warning.empty()) {
    PyErr_WarnEx(PyExc_RuntimeWarning, warning.c_str(), 1);
  }
  const TimePoint end = clock.now() + from_seconds(o.duration_s);
  while (o.duration_s <= 0.0 || clock.now() < end) {
    {
      const py::gil_scoped_release release;
      std::this_thread::sleep_for(10ms);
    }
    if (PyErr_CheckSignals() != 0) {
      throw py::error_already_set();  // Ctrl-C: the Rig's destructor stops the loop cleanly
    }
    if (!o.callback.is_none()) {
      rig->drain(o.callback);
    }
  }
  {
    const py::gil_scoped_release release;
    rig->bridge().stop();
  }
  if (!o.callback.is_none()) {
    rig->drain(o.callback);
  }
  return rig->stats(!o.callback.is_none());
}

RunOptions options_from(const std::string& source, const std::string& device, double duration_s,
                        double rate_hz, double max_force_N, double feedback_gain_per_s,
                        double footprint_cells, bool realtime, const py::object& callback,
                        std::uint64_t decimation) {
  RunOptions o;
  o.source = source;
  o.device = device;
  o.duration_s = duration_s;
  o.bridge.rate_hz = rate_hz;
  o.bridge.max_force_N = max_force_N;
  o.bridge.feedback_gain_per_s = feedback_gain_per_s;
  o.bridge.footprint_cells = footprint_cells;
  o.bridge.realtime = realtime;
  o.callback = callback;
  o.decimation = decimation;
  if (!(duration_s >= 0.0) || !(rate_hz > 0.0)) {
    throw InvalidArgument("duration_s must be >= 0 and rate_hz > 0 (got " + std::to_string(duration_s) +
                          ", " + std::to_string(rate_hz) + ")");
  }
  if (!callback.is_none() && PyCallable_Check(callback.ptr()) == 0) {
    throw InvalidArgument("callback must be callable (it gets one mrskin.bridge.TickSample), or None");
  }
  return o;
}

constexpr const char* kRunArgs =
    "source: a scene name (scene_names()) or a stream URI (replay://FILE, udp://HOST:PORT, ...;\n"
    "  docs/sources.md). device: mock://[PROFILE][?seed=N&finger=SCENE...] or a unit's URI.\n"
    "callback(sample): called with every `decimation`-th rendered tick (a TickSample) on this\n"
    "  thread, after the tick: never inside it.\n"
    "Returns the statistics as a dict (docs/statistics.md; with a callback also callback_samples\n"
    "and callback_dropped). Raises InvalidArgument, ProfileNotFound, DeviceNotFound, ... at setup.";

}  // namespace

void bind_bridge(py::module_& m) {
  py::class_<TickSample>(
      m, "TickSample",
      "One rendered tick. target_N: the tissue law clamped into the envelope, per fluid cell.\n"
      "observed_force_N: the observer's estimate of the rendered force (what hardware knows).\n"
      "true_force_N: the plant's true contact force on the mock (None on hardware).")
      .def_readonly("t_s", &TickSample::t_s, "Since the bridge's first tick, s.")
      .def_readonly("target_N", &TickSample::target_N)
      .def_readonly("observed_force_N", &TickSample::observed_force_N)
      .def_readonly("true_force_N", &TickSample::true_force_N);

  m.def(
      "scene_names",
      [] {
        std::vector<std::string> names;
        for (const std::string_view n : bridge::scene_names()) {
          names.emplace_back(n);
        }
        return names;
      },
      "The built-in scenes (docs/bridge.md): demo, the organs of the paper's Table 2, sweep, ...");
  const auto simulated = [](const std::string& source, const std::string& device, double duration_s,
                            double rate_hz, double max_force_N, double feedback_gain_per_s,
                            double footprint_cells, const py::object& callback, std::uint64_t decimation) {
    return run_simulated(options_from(source, device, duration_s, rate_hz, max_force_N, feedback_gain_per_s,
                                      footprint_cells, false, callback, decimation));
  };
  m.def("run_simulated", simulated, py::arg("source") = "demo", py::arg("device") = "mock://",
        py::arg("duration_s") = 5.0, py::arg("rate_hz") = 1000.0, py::arg("max_force_N") = 2.0,
        py::arg("feedback_gain_per_s") = 30.0, py::arg("footprint_cells") = 1.5,
        py::arg("callback") = py::none(), py::arg("decimation") = 10,
        (std::string(
             "Runs the bridge on the simulated clock: deterministic, as fast as it computes\n"
             "(the C++ tests' closed loop; the same scene, seed and options give the same statistics).\n") +
         kRunArgs)
            .c_str());
  const auto realtime = [](const std::string& source, const std::string& device, double duration_s,
                           double rate_hz, double max_force_N, double feedback_gain_per_s,
                           double footprint_cells, bool rt, const py::object& callback,
                           std::uint64_t decimation) {
    return run_realtime(options_from(source, device, duration_s, rate_hz, max_force_N, feedback_gain_per_s,
                                     footprint_cells, rt, callback, decimation));
  };
  m.def("run_realtime", realtime, py::arg("source") = "demo", py::arg("device") = "mock://",
        py::arg("duration_s") = 5.0, py::arg("rate_hz") = 1000.0, py::arg("max_force_N") = 2.0,
        py::arg("feedback_gain_per_s") = 30.0, py::arg("footprint_cells") = 1.5, py::arg("realtime") = false,
        py::arg("callback") = py::none(), py::arg("decimation") = 10,
        (std::string("Runs the bridge in real time on its own loop thread for duration_s (0: until Ctrl-C).\n"
                     "Ctrl-C (KeyboardInterrupt) stops the loop, releases the unit and re-raises.\n"
                     "realtime=True asks SCHED_FIFO and mlockall for the loop (docs/install.md), warning\n"
                     "(RuntimeWarning) when refused.\n") +
         kRunArgs)
            .c_str());
}

}  // namespace mrskin::python
