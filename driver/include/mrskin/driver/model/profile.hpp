// Device profiles: every parameter of one MR skin, with its SI unit in its name, read from a
// TOML file (driver/profiles/*.toml; installed to share/mrskin/profiles). The layout is data:
// any rows x cols checkerboard (fluid cell where row + col is even), the hydraulic graph and
// the sensors. See docs/model.md ("Profiles") for the file format.
//
// Loading happens at setup and throws mrskin::InvalidArgument naming the file, the field and
// the reason ("mr-skin-5x5.toml: [valve] gap_m: must be > 0 (got -0.001)").
#pragma once

#include <cstddef>
#include <cstdint>
#include <optional>
#include <string>
#include <string_view>
#include <vector>

#include "mrskin/driver/export.hpp"
#include "mrskin/driver/model/coil.hpp"
#include "mrskin/driver/model/fluid.hpp"
#include "mrskin/driver/model/magnetic.hpp"
#include "mrskin/driver/model/membrane.hpp"
#include "mrskin/driver/model/valve.hpp"
#include "mrskin/protocol/bus_budget.hpp"

namespace mrskin::model {

enum class SensorQuantity : unsigned char { displacement, force, pressure };
MRSKIN_DRIVER_API const char* to_string(SensorQuantity q) noexcept;
// The SI unit of a quantity ("m", "N", "Pa").
MRSKIN_DRIVER_API const char* unit_of(SensorQuantity q) noexcept;

enum class PlaceKind : unsigned char { fluid_cell, valve, reservoir };

struct SensorSpec {
  SensorQuantity quantity = SensorQuantity::displacement;
  PlaceKind place = PlaceKind::valve;
  int row = 0;
  int col = 0;
  std::size_t index = 0;    // fluid-cell or valve index in the grid's order (GridLayout)
  double resolution = 0.0;  // one count, in the quantity's SI unit
  double noise_std = 0.0;   // standard deviation, same unit
};

enum class NodeKind : unsigned char { fluid_cell, chamber, reservoir };
struct NodeRef {
  NodeKind kind = NodeKind::fluid_cell;
  std::uint32_t index = 0;  // fluid-cell index, or the valve index whose chamber it is; 0 for the reservoir
  bool operator==(const NodeRef&) const = default;
};

// One passage of the valve geometry between two nodes, magnetised by a valve's coil.
struct HydraulicLink {
  NodeRef a;
  NodeRef b;
  std::int32_t valve = -1;  // coil that magnetises it (valve index), -1: unmagnetised
};

struct ReservoirParams {
  double initial_pressure_Pa = 0.0;    // p0, gauge
  double compliance_m3_per_Pa = 1e-9;  // volume taken per pascal
};

// The load case the default coil was designed for (documentation and tests).
struct DesignPoint {
  double force_range_N = 2.0;
  double indentation_m = 5e-3;
  int row = 2;
  int col = 2;
};

struct MRSKIN_DRIVER_API DeviceProfile {
  std::string name;
  std::string description;
  std::string origin;  // file it was read from, or "<text>"
  int rows = 5;
  int cols = 5;
  double cell_pitch_m = 0.03;
  double cell_depth_m = 0.04;
  FluidParams fluid;
  ValveGeometry valve;
  MagneticCircuitParams magnetic;  // fluid_gap_m always equals valve.gap_m
  std::string core_material;
  CoilParams coil;
  MembraneParams membrane;
  double finger_radius_m = 6e-3;
  ReservoirParams reservoir;
  std::string topology;  // "chamber", "direct" or "explicit"
  std::vector<HydraulicLink> links;
  std::vector<SensorSpec> sensors;
  DesignPoint design;
  // [interface] bus: the bus a unit of this design is built with ("hid-fs", "hid-hs", "can",
  // "canfd"), which mock:// models when its URI names no bus=; "none" (nullopt) for a design
  // with no bus yet, which the mock links ideally. A 16 x 16 unit's telemetry alone needs six
  // full-speed reports a millisecond, so fingertip-16x16 says "hid-hs".
  std::optional<protocol::BusKind> bus = protocol::BusKind::hid_full_speed;

  // Radius of the circle with the cell's area (a = pitch / sqrt(pi)), m.
  [[nodiscard]] double cell_radius_m() const noexcept;
};

// Parses and validates a profile; throws InvalidArgument.
MRSKIN_DRIVER_API DeviceProfile parse_profile(std::string_view toml_text, const std::string& origin);
// Reads a file, or finds a profile by name ("mr-skin-5x5") in the search path.
MRSKIN_DRIVER_API DeviceProfile load_profile(const std::string& path_or_name);
// The default profile: the paper's 5 x 5 ("mr-skin-5x5").
MRSKIN_DRIVER_API DeviceProfile default_profile();
inline constexpr const char* kDefaultProfileName = "mr-skin-5x5";

// Directories searched for a profile name, in order: $MRSKIN_PROFILE_PATH (colon-separated),
// then relative to the directory the driver library was loaded from: the installed
// share/mrskin/profiles (wherever the prefix is), then mrskin-profiles beside the library (a
// build tree's link to driver/profiles).
MRSKIN_DRIVER_API std::vector<std::string> profile_search_path();
// The file a name resolves to; throws InvalidArgument listing where it looked.
MRSKIN_DRIVER_API std::string find_profile(const std::string& name);

// A device profile found by name or path, with the text it was read from.
struct LoadedProfile {
  DeviceProfile profile;
  std::string text;
  std::string path;
};
// name_or_path: "" or "default" (the default profile, mr-skin-5x5), a profile name looked up in
// profile_search_path(), or a file path (containing '/' or ending in .toml). Throws
// ProfileNotFound (listing the search path and the names found there) or InvalidArgument (a
// file that cannot be read or parsed).
MRSKIN_DRIVER_API LoadedProfile load_profile_with_text(std::string_view name_or_path);
// The profile names (file stems) in the search path, sorted, without duplicates.
MRSKIN_DRIVER_API std::vector<std::string> available_profile_names();

}  // namespace mrskin::model
