// Exit codes shared by mrskin's executables, and the one place that maps setup exceptions
// to them with the exception's message (which says what to do).
#pragma once

#include <spdlog/spdlog.h>

#include <exception>

#include "mrskin/driver/errors.hpp"

namespace mrskin::tools {

enum ExitCode : int {
  kOk = 0,
  kFailure = 1,      // runtime failure
  kUsage = 2,        // bad argument, URI or profile
  kNoDevice = 3,     // device not found or access denied
  kMismatch = 4,     // protocol version mismatch
  kBusy = 5,         // device owned by another process
  kUnavailable = 69  // command not in this build (sysexits EX_UNAVAILABLE)
};

// Call only from a catch block: logs the exception in flight as an error and returns its exit
// code.
inline int exit_code_for_current_exception() noexcept {
  int code = kFailure;
  const char* what = "unknown exception";
  try {
    throw;
  } catch (const InvalidArgument& e) {
    code = kUsage;
    what = e.what();
  } catch (const DeviceNotFound& e) {
    code = kNoDevice;
    what = e.what();
  } catch (const PermissionDenied& e) {
    code = kNoDevice;
    what = e.what();
  } catch (const DeviceBusy& e) {
    code = kBusy;
    what = e.what();
  } catch (const ProtocolMismatch& e) {
    code = kMismatch;
    what = e.what();
  } catch (const std::exception& e) {
    what = e.what();
  } catch (...) {
  }
  spdlog::error("{}", what);  // the tool's logger (logging.hpp): journald priority under systemd
  return code;
}

}  // namespace mrskin::tools
