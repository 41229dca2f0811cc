// The daemon's reload (SIGHUP or the control socket's `reload`): which settings a running daemon
// takes, and how it swaps a bridge, a source or a loop between two ticks.
#include <fmt/format.h>

#include <memory>
#include <mutex>
#include <string>
#include <vector>

#include "daemon.hpp"
#include "mrskin/eval/truth_scorer.hpp"

namespace mrskin::bridged {

using bridge::Bridge;

namespace {

// Settings that only a restart can change keep their running values; each kept change is logged.
void keep_restart_only_settings(const Settings& running, Settings& next, std::vector<std::string>& log) {
  if (next.device != running.device) {
    log.push_back(fmt::format("reload: device {} -> {} needs a restart (the device stays open); kept {}",
                              running.device, next.device, running.device));
    next.device = running.device;
  }
  if (next.socket != running.socket || next.max_clients != running.max_clients ||
      next.idle_timeout_s != running.idle_timeout_s) {
    log.emplace_back("reload: [control] changes need a restart; kept the current socket");
    next.socket = running.socket;
    next.max_clients = running.max_clients;
    next.idle_timeout_s = running.idle_timeout_s;
  }
  if (next.topics_namespace != running.topics_namespace || next.topics_domain != running.topics_domain ||
      next.topics_rate_hz != running.topics_rate_hz) {
    log.emplace_back("reload: [topics] changes need a restart; kept the current topics");
    next.topics_namespace = running.topics_namespace;
    next.topics_domain = running.topics_domain;
    next.topics_rate_hz = running.topics_rate_hz;
  }
}

bool same_mapping(const bridge::WorkspaceMapping& m0, const bridge::WorkspaceMapping& m1) noexcept {
  return m0.origin_x_m == m1.origin_x_m && m0.origin_y_m == m1.origin_y_m &&
         m0.cells_per_m == m1.cells_per_m && m0.rotation_rad == m1.rotation_rad &&
         m0.mirror_x == m1.mirror_x && m0.mirror_y == m1.mirror_y;
}

}  // namespace

Daemon::ReloadPlan Daemon::plan_reload(const Settings& next) const {
  const Settings& old = settings_;
  ReloadPlan plan;
  plan.mapping_changed = !same_mapping(old.mapping, next.mapping);
  plan.source_changed = next.source != old.source || !same_source_options(next, old) ||
                        (plan.mapping_changed && source_.scene != nullptr);
  plan.loop_changed = next.rate_hz != old.rate_hz || next.realtime != old.realtime ||
                      next.rt_priority != old.rt_priority || next.cpu != old.cpu;
  plan.bridge_changed = plan.loop_changed || plan.mapping_changed || plan.source_changed ||
                        next.feedback_gain_per_s != old.feedback_gain_per_s ||
                        next.footprint_cells != old.footprint_cells ||
                        next.resend_period_s != old.resend_period_s ||
                        next.stale_hold_s != old.stale_hold_s || next.stale_fade_s != old.stale_fade_s;
  return plan;
}

// Without a new source the bridge keeps every state (observer, tissue fit, feedback, latches) and
// takes the new tuning between two ticks: bumpless. A new source needs a new bridge, whose tissue
// fit and observer start afresh. Everything new is built while the old loop runs (the Bridge
// constructor reads only the session's identity and profile, fixed since the handshake), so the
// device misses a tick or two at the swap, far below its watchdog. False: refused, logged, and
// the daemon runs on as before.
bool Daemon::apply_reload(const Settings& next, const ReloadPlan& plan, std::vector<std::string>& log) {
  OpenedSource fresh;
  std::unique_ptr<bridge::Scene> finger;
  std::unique_ptr<WatchedSource> watched;
  std::unique_ptr<Bridge> b;
  std::unique_ptr<bridge::RealtimeLoop> new_loop;
  try {
    if (plan.mapping_changed && finger_scene_) {
      finger = open_finger_scene(next);
      finger->set_start(t0_);  // the finger carries on where it is, mapped anew
    }
    if (plan.source_changed) {
      fresh = open_source(next, clock_, waiter_.get());
      if (fresh.scene != nullptr) {
        fresh.scene->set_start(t0_);  // the script carries on where it is
      }
      watched = std::make_unique<WatchedSource>(*fresh.source, recorder_.get());
      b = std::make_unique<Bridge>(*dev_.session, *watched, bridge_options(next));
    }
    if (plan.loop_changed) {
      new_loop = std::make_unique<bridge::RealtimeLoop>(clock_, *this, loop_options(next, waiter_.get()));
    }
  } catch (const std::exception& e) {
    log.push_back(fmt::format("reload refused, running on as before: {}", e.what()));
    return false;
  }
  if (loop_) {
    loop_->stop();  // only the loop: the recording and the skin's topics go on across a reload
  }
  if (b) {
    std::unique_ptr<eval::TruthScorer> scorer = make_scorer(*b);
    if (const unsigned char halt = operator_halt_.load(); halt != 0) {
      b->request(static_cast<Bridge::Request>(halt));  // a reload never re-enables
    }
    ticks_base_.fetch_add(bridge_->live_ticks());
    ticks_.set(0);
    bridge_ = std::move(b);  // old bridge first, then its scorer, the wrapper and the source it read
    scorer_ = std::move(scorer);
    watched_ = std::move(watched);
    {
      const std::lock_guard<std::mutex> lock(shown_mutex_);  // stream_warning() on the control thread
      source_ = std::move(fresh);
    }
    events_seen_ = 0;
    finger_t0_ = t0_;  // in step with the new source: a scene's carries on, a stream's first sample
    finger_waits_ = source_.stream != nullptr && source_.stream->stats().accepted == 0;
  } else {
    try {
      bridge_->retune(bridge_tuning(next));
    } catch (const std::exception& e) {
      log.push_back(fmt::format("reload refused, running on as before: {}", e.what()));
      (void)start();
      return false;
    }
  }
  if (finger) {
    finger_scene_ = std::move(finger);
  }
  if (new_loop) {
    loop_ = std::move(new_loop);
  }
  drive_finger();  // before the new loop's first tick (the main loop, loaded, came 0.5 s late)
  return true;
}

std::vector<std::string> Daemon::reload(Settings next) {
  std::vector<std::string> log;
  keep_restart_only_settings(settings_, next, log);
  if (!next.rate_given) {
    next.rate_hz = default_rate_hz_;  // what the bus carries, as at start
  }
  const ReloadPlan plan = plan_reload(next);
  if (plan.bridge_changed) {
    if (!apply_reload(next, plan, log)) {
      return log;
    }
    settings_ = next;
    if (const std::string warning = start(); !warning.empty()) {
      log.push_back("warning: " + warning);
    }
    if (plan.loop_changed && !bus_warning().empty()) {  // a new rate: its budget
      log.push_back("warning: " + bus_warning());
    }
    log.push_back(fmt::format(
        "reload: {} (rate {} Hz, feedback gain {} /s, footprint {} cells, mapping origin ({}, {}) m, {} "
        "cells/m, stale hold {} s, fade {} s, source {})",
        plan.source_changed ? "new bridge on the open device for the new source, starting afresh"
                            : "bridge retuned in place, every state kept",
        next.rate_hz, next.feedback_gain_per_s, next.footprint_cells, next.mapping.origin_x_m,
        next.mapping.origin_y_m, next.mapping.cells_per_m, next.stale_hold_s, next.stale_fade_s,
        next.source));
  } else {
    log.emplace_back("reload: no bridge change; the loop runs on");
  }
  settings_ = next;
  {
    const std::lock_guard<std::mutex> lock(shown_mutex_);
    shown_ = settings_;
  }
  reloads_.fetch_add(1);
  return log;
}

}  // namespace mrskin::bridged
