// `mrskinctl model ...` in process: JSON with unit-suffixed keys, clear errors, exit codes.
#include <gtest/gtest.h>

#include <cstdio>
#include <cstdlib>
#include <string>
#include <vector>

#include "model_command.hpp"

namespace {

const std::string kDir = MRSKIN_TEST_PROFILE_DIR;

struct CliRun {
  int code = -1;
  std::string out;
  std::string err;
};

// Runs "model <args...>" through CLI11 as mrskinctl would; CLI11's own parse errors give its
// exit code (non-zero).
CliRun run(std::vector<std::string> args) {
  setenv("MRSKIN_PROFILE_PATH", kDir.c_str(), 1);
  char* out_buf = nullptr;
  char* err_buf = nullptr;
  std::size_t out_len = 0;
  std::size_t err_len = 0;
  std::FILE* out = open_memstream(&out_buf, &out_len);
  std::FILE* err = open_memstream(&err_buf, &err_len);
  CliRun r;
  {
    mrskin::tools::CliApp app{"test"};
    int code = 0;
    mrskin::ctl::add_model_command(app.root(), code, out, err);
    args.insert(args.begin(), "model");
    const mrskin::tools::CliParse parsed = app.parse_quietly(args);
    r.code = parsed.run ? code : parsed.exit_code;
    if (!parsed.run) {
      std::fputs((parsed.message + "\n").c_str(), err);
    }
  }
  std::fclose(out);
  std::fclose(err);
  r.out = out_buf;
  r.err = err_buf;
  std::free(out_buf);
  std::free(err_buf);
  return r;
}

bool has(const std::string& s, const std::string& needle) { return s.find(needle) != std::string::npos; }

double field(const std::string& json, const std::string& key) {
  const auto pos = json.find("\"" + key + "\": ");
  EXPECT_NE(pos, std::string::npos) << key << " in " << json;
  return pos == std::string::npos ? 0.0 : std::strtod(json.c_str() + pos + key.size() + 4, nullptr);
}

TEST(ModelCli, ValvePressureAndFlowBothWays) {
  const CliRun p = run({"valve", "--q", "1e-6", "--tau-y", "100"});
  ASSERT_EQ(p.code, 0) << p.err;
  EXPECT_TRUE(has(p.out, "\"dp_pa\": ")) << p.out;
  EXPECT_TRUE(has(p.out, "\"q_m3_s\": 1e-06")) << p.out;
  EXPECT_TRUE(has(p.out, "\"tau_y_pa\": 100")) << p.out;
  EXPECT_TRUE(has(p.out, "\"turbulent\": false")) << p.out;
  const double dp = field(p.out, "dp_pa");
  const CliRun q = run({"valve", "--dp", std::to_string(dp), "--tau-y", "100"});
  ASSERT_EQ(q.code, 0) << q.err;
  EXPECT_NEAR(field(q.out, "q_m3_s"), 1e-6, 1e-11);
  for (const char* m : {"fast", "wereley-pang"}) {
    const CliRun a = run({"valve", "--q", "1e-6", "--tau-y", "100", "--method", m});
    ASSERT_EQ(a.code, 0) << a.err;
    EXPECT_NEAR(field(a.out, "dp_pa") / dp, 1.0, 0.04) << m;
  }
  // Geometry and fluid from the command line.
  const CliRun g = run({"valve", "--q", "1e-6", "--tau-y", "0", "--gap", "0.5e-3", "--width", "0.03",
                        "--length", "0.024", "--viscosity", "0.1"});
  ASSERT_EQ(g.code, 0) << g.err;
  EXPECT_NEAR(field(g.out, "dp_pa"), 12 * 0.1 * 1e-6 * 0.024 / (0.03 * 1.25e-10), 1e-6);
}

TEST(ModelCli, FluidCoilMembraneCellProfile) {
  const CliRun f = run({"fluid", "--h", "1e4"});
  ASSERT_EQ(f.code, 0) << f.err;
  EXPECT_NEAR(field(f.out, "tau_y_pa"), 3000.0, 100.0);
  EXPECT_TRUE(has(f.out, "\"b_t\": "));
  EXPECT_TRUE(has(f.out, "\"h_a_m\": 10000"));

  const CliRun c = run({"coil", "--current", "0.05"});
  ASSERT_EQ(c.code, 0) << c.err;
  EXPECT_GT(field(c.out, "h_a_m"), 0.0);
  EXPECT_GT(field(c.out, "b_t"), 0.0);
  EXPECT_GT(field(c.out, "tau_y_pa"), 0.0);

  const CliRun m = run({"membrane", "--deflection", "5e-3"});
  ASSERT_EQ(m.code, 0) << m.err;
  EXPECT_TRUE(has(m.out, "\"regime\": \"membrane\""));
  EXPECT_TRUE(has(m.out, "\"eq6_valid\": false"));
  EXPECT_GT(field(m.out, "force_n"), 0.0);

  const CliRun cell =
      run({"cell", "--cell", "2,2", "--displacement", "5e-3", "--velocity", "0.001", "--current", "0.08"});
  ASSERT_EQ(cell.code, 0) << cell.err;
  const double force = field(cell.out, "force_n");
  EXPECT_GE(force, field(cell.out, "force_min_n"));
  EXPECT_LE(force, field(cell.out, "force_max_n"));
  EXPECT_TRUE(has(cell.out, "\"envelope\": {"));

  const CliRun prof = run({"profile"});
  ASSERT_EQ(prof.code, 0) << prof.err;
  EXPECT_TRUE(has(prof.out, "\"fluid_cells\": 13"));
  EXPECT_GT(field(prof.out, "fraction_of_current_range"), 0.7);

  const CliRun palm = run({"--profile", "palm-64x64", "profile"});
  ASSERT_EQ(palm.code, 0) << palm.err;
  EXPECT_TRUE(has(palm.out, "\"rows\": 64"));
}

TEST(ModelCli, BadInputIsAClearErrorAndNonZeroExit) {
  struct Case {
    std::vector<std::string> args;
    std::string needle;
  };
  const std::vector<Case> cases = {
      {{"valve", "--q", "nan", "--tau-y", "100"}, "--q must be a finite number"},
      {{"valve", "--q", "1e-6", "--tau-y", "-5"}, "--tau-y must be >= 0"},
      {{"valve", "--q", "1e-6", "--dp", "100", "--tau-y", "5"}, "exactly one of --dp"},
      {{"valve", "--q", "1e-6", "--tau-y", "5", "--method", "magic"}, "--method must be"},
      {{"valve", "--q", "1e-6", "--tau-y", "5", "--gap", "-1"}, "gap_m: must be > 0"},
      {{"fluid", "--h", "inf"}, "--h must be a finite number"},
      {{"coil", "--current", "5"}, "outside the profile's range"},
      {{"membrane", "--deflection", "-1e-3"}, "outside 0.."},
      {{"cell", "--cell", "2,3", "--displacement", "1e-3", "--velocity", "0", "--current", "0"},
       "not a fluid cell"},
      {{"cell", "--cell", "x", "--displacement", "1e-3", "--velocity", "0", "--current", "0"}, "ROW,COL"},
      {{"cell", "--cell", "2,2", "--displacement", "1", "--velocity", "0", "--current", "0"}, "cell_depth_m"},
      {{"--profile", "/nonexistent/p.toml", "profile"}, "cannot be read"},
  };
  for (const Case& c : cases) {
    const CliRun r = run(c.args);
    EXPECT_NE(r.code, 0) << c.needle;
    EXPECT_TRUE(has(r.err, c.needle)) << r.err;
    EXPECT_TRUE(r.out.empty()) << r.out;
  }
  // CLI11's own errors (missing required option, not a number) are non-zero too.
  EXPECT_NE(run({"valve", "--q", "1e-6"}).code, 0);
  EXPECT_NE(run({"fluid", "--h", "abc"}).code, 0);
  EXPECT_NE(run({}).code, 0);
}

TEST(ModelCli, PaperEq3AndHysteresisBranch) {
  const CliRun e =
      run({"--profile", "paper-table4", "valve", "--dp", "2e6", "--tau-y", "1e4", "--method", "paper-eq3"});
  ASSERT_EQ(e.code, 0) << e.err;
  EXPECT_LT(field(e.out, "q_m3_s"), 0.0);
  EXPECT_GT(field(e.out, "q_exact_m3_s"), 0.0);
  EXPECT_TRUE(has(e.out, "\"valid\": false"));
  EXPECT_NE(run({"valve", "--q", "1e-6", "--tau-y", "1", "--method", "paper-eq3"}).code, 0);
  // Low-carbon steel remembers 2 A: at zero current the gap still holds kilopascals of yield stress.
  const CliRun h = run({"--profile", "paper-table4", "coil", "--current", "0", "--from", "2"});
  ASSERT_EQ(h.code, 0) << h.err;
  EXPECT_EQ(field(h.out, "tau_y_pa"), 0.0);
  const auto pos = h.out.find("\"hysteresis\"");
  ASSERT_NE(pos, std::string::npos);
  EXPECT_GT(field(h.out.substr(pos), "tau_y_pa"), 1000.0);
}

}  // namespace
