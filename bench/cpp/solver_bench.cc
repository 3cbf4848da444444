// Solver-core benchmark without Python in the loop (issue 7, item 6).
//
// Replays problems saved from the simulator by bench/_common.py (ProblemLog) into the C++
// BundleAdjuster and SlidingWindow of fusedmosaic_core and times them with std::chrono:
//   * "ba" files: the calls a BA / BA+EMT run made (frames, pairs with their points, plane),
//     then Solve(). Each repeat builds a fresh adjuster; build and Solve() are timed apart.
//   * "window" files: the call log of the LBAVis+EMT sliding window of a streamed sequence
//     (bootstrap-fixed frames, new frames, pairs, steps with their keyframes, gating redos,
//     forgets). Each repeat replays the whole log into a fresh window; every Step()/Redo() is
//     timed, giving the per-step latency distribution.
// The files also hold the poses Python obtained ("expect"), so each replay reports its largest
// pose difference from the recorded run: the replay is the same problem, not a look-alike.
//
// Usage: fusedmosaic_solver_bench [--repeats N] [--threads T] --out results.json FILE...
// --threads overrides the num_threads stored in a file (0 = keep).
//
// File format (text, whitespace-separated tokens, one record per line):
//   fusedmosaic-problem 1 ba|window
//   K k00 k01 k02 k10 k11 k12 k20 k21 k22
//   costs sigma_v_px loss loss_scale_px linear_solver residual_blocks max_iterations
//         function_tolerance gradient_tolerance parameter_tolerance num_threads use_emt
//         use_motion_prior
//   emt_sigma s1..s6          motion_sigma s1..s6
//   plane_std plane_std plane_std_paired_only      (0|1 each; optional, 0 0 when absent)
//   window window_size num_new fold_fixed_cameras             (window files only)
//   add_frame id has_initial [x1..x6] has_emt [z1..z6] fixed [motion_ratio motion_sigma_scale]
//     (ba: fixed is ignored; the C_p timing is optional, 1 1 when absent)
//   add_pair l m n            followed by n lines "x_l y_l x_m y_m" (pixels)
//   set_plane p1 p2 p3
//   solve                     (ba)
//   step nk k1..knk           redo nf f1..fnf nk k1..knk      forget n id1..idn
//   set_emt_sigma_scale id s  set_constant_frame id 0|1       set_pose id x1..x6
//   set_sigma_v px            (window)
//   expect id x1..x6          expect_plane p1 p2 p3           (poses after the last solve/step)
//   end
#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <fstream>
#include <iostream>
#include <limits>
#include <map>
#include <memory>
#include <optional>
#include <sstream>
#include <stdexcept>
#include <cstdlib>
#include <string>
#include <vector>

#include "fusedmosaic/problem/bundle_adjuster.h"
#include "fusedmosaic/problem/sliding_window.h"

namespace {

using fusedmosaic::BundleAdjuster;
using fusedmosaic::BundleAdjusterOptions;
using fusedmosaic::SlidingWindow;
using fusedmosaic::SlidingWindowOptions;
using fusedmosaic::Vector6d;
using Clock = std::chrono::steady_clock;
using Points = Eigen::Matrix<double, Eigen::Dynamic, 2>;

// One recorded call. Points are stored once and shared by every repeat.
struct Call {
  std::string name;
  std::vector<int> ids;       // frame ids (add_frame: {id}; add_pair: {l, m}; step: keyframes)
  std::vector<int> ids2;      // redo: keyframes
  std::optional<Vector6d> a;  // initial pose / set_pose / expect
  std::optional<Vector6d> b;  // EMT measurement
  bool flag = false;          // fixed / constant; step / redo: hold pi
  double value = 0.0;         // sigma scale
  double ratio = 1.0, scale = 1.0;  // add_frame: C_p timing
  Eigen::Vector3d plane = Eigen::Vector3d::Zero();
  std::shared_ptr<Points> points_l, points_m;
};

struct Problem {
  std::string path;
  std::string kind;  // "ba" | "window"
  Eigen::Matrix3d K;
  BundleAdjusterOptions costs;
  SlidingWindowOptions window;
  std::vector<Call> calls;
  std::map<int, Vector6d> expect;  // final poses of the recorded run (ba), or per step (window)
  std::optional<Eigen::Vector3d> expect_plane;
  int num_frames = 0, num_pairs = 0;
  long num_correspondences = 0;
};

[[noreturn]] void Fail(const std::string& path, int line, const std::string& what) {
  throw std::runtime_error(path + ":" + std::to_string(line) + ": " + what);
}

Vector6d ReadPose(std::istringstream& in, const std::string& path, int line) {
  Vector6d x;
  for (int i = 0; i < 6; ++i) {
    if (!(in >> x[i])) Fail(path, line, "expected 6 pose values");
  }
  return x;
}

std::vector<int> ReadIds(std::istringstream& in, const std::string& path, int line) {
  int n = 0;
  if (!(in >> n) || n < 0) Fail(path, line, "expected a count of ids");
  std::vector<int> ids(n);
  for (int& id : ids) {
    if (!(in >> id)) Fail(path, line, "expected " + std::to_string(n) + " ids");
  }
  return ids;
}

Problem Load(const std::string& path) {
  std::ifstream file(path);
  if (!file) throw std::runtime_error(path + ": cannot open");
  Problem p;
  p.path = path;
  std::string text;
  int line = 0;
  auto next = [&](std::istringstream& in) {
    if (!std::getline(file, text)) return false;
    ++line;
    in.clear();
    in.str(text);
    return true;
  };
  std::istringstream in;
  if (!next(in)) Fail(path, line, "empty file");
  std::string magic;
  int version = 0;
  in >> magic >> version >> p.kind;
  if (magic != "fusedmosaic-problem" || version != 1 || (p.kind != "ba" && p.kind != "window")) {
    Fail(path, line, "expected 'fusedmosaic-problem 1 ba|window', got '" + text + "'");
  }
  bool ended = false;
  while (!ended && next(in)) {
    std::string name;
    if (!(in >> name)) continue;
    Call c;
    c.name = name;
    if (name == "K") {
      for (int i = 0; i < 9; ++i) {
        if (!(in >> p.K(i / 3, i % 3))) Fail(path, line, "K: expected 9 values");
      }
      continue;
    } else if (name == "costs") {
      auto& o = p.costs;
      int use_emt = 1, use_motion = 1;
      if (!(in >> o.sigma_v_px >> o.loss >> o.loss_scale_px >> o.linear_solver >>
            o.residual_blocks >> o.max_iterations >> o.function_tolerance >> o.gradient_tolerance >>
            o.parameter_tolerance >> o.num_threads >> use_emt >> use_motion)) {
        Fail(path, line, "costs: expected 12 fields");
      }
      o.use_emt = use_emt != 0;
      o.use_motion_prior = use_motion != 0;
      continue;
    } else if (name == "emt_sigma") {
      p.costs.emt_sigma = ReadPose(in, path, line);
      continue;
    } else if (name == "motion_sigma") {
      p.costs.motion_sigma = ReadPose(in, path, line);
      continue;
    } else if (name == "plane_std") {
      int on = 0, paired_only = 0;
      if (!(in >> on >> paired_only)) {
        Fail(path, line, "plane_std: expected plane_std plane_std_paired_only");
      }
      p.costs.plane_std = on != 0;
      p.costs.plane_std_paired_only = paired_only != 0;
      continue;
    } else if (name == "window") {
      int fold = 1;
      if (!(in >> p.window.window_size >> p.window.num_new >> fold)) {
        Fail(path, line, "window: expected window_size num_new fold_fixed_cameras");
      }
      p.window.fold_fixed_cameras = fold != 0;
      continue;
    } else if (name == "add_frame") {
      int id = 0, has_initial = 0, has_emt = 0, fixed = 0;
      if (!(in >> id >> has_initial)) Fail(path, line, "add_frame: expected id has_initial");
      if (has_initial) c.a = ReadPose(in, path, line);
      if (!(in >> has_emt)) Fail(path, line, "add_frame: expected has_emt");
      if (has_emt) c.b = ReadPose(in, path, line);
      if (!(in >> fixed)) Fail(path, line, "add_frame: expected fixed");
      // optional C_p timing; the scale may be "inf" (a released prior), which operator>>
      // does not parse, so both are read as words
      std::string ratio, scale;
      if (in >> ratio >> scale) {
        c.ratio = std::strtod(ratio.c_str(), nullptr);
        c.scale = std::strtod(scale.c_str(), nullptr);
      } else {
        c.ratio = c.scale = 1.0;
      }
      c.ids = {id};
      c.flag = fixed != 0;
      ++p.num_frames;
    } else if (name == "add_pair") {
      int l = 0, m = 0, n = 0;
      if (!(in >> l >> m >> n) || n < 1) Fail(path, line, "add_pair: expected l m n (n >= 1)");
      c.ids = {l, m};
      c.points_l = std::make_shared<Points>(n, 2);
      c.points_m = std::make_shared<Points>(n, 2);
      for (int i = 0; i < n; ++i) {
        std::istringstream row;
        if (!next(row)) Fail(path, line, "add_pair: file ends inside the points");
        auto& pl = *c.points_l;
        auto& pm = *c.points_m;
        if (!(row >> pl(i, 0) >> pl(i, 1) >> pm(i, 0) >> pm(i, 1))) {
          Fail(path, line, "add_pair: expected 'x_l y_l x_m y_m'");
        }
      }
      ++p.num_pairs;
      p.num_correspondences += n;
    } else if (name == "set_plane" || name == "expect_plane") {
      for (int i = 0; i < 3; ++i) {
        if (!(in >> c.plane[i])) Fail(path, line, name + ": expected 3 values");
      }
      if (name == "expect_plane") {
        p.expect_plane = c.plane;
        continue;
      }
    } else if (name == "solve") {
    } else if (name == "step" || name == "redo") {
      c.ids = ReadIds(in, path, line);
      if (name == "redo") c.ids2 = ReadIds(in, path, line);
      std::string hold;  // optional: the step holds pi (SlidingWindow::Step's hold_plane)
      if (in >> hold) {
        if (hold != "hold") Fail(path, line, name + ": expected 'hold' or the end of the line");
        c.flag = true;
      }
    } else if (name == "forget") {
      c.ids = ReadIds(in, path, line);
    } else if (name == "set_emt_sigma_scale") {
      int id = 0;
      if (!(in >> id >> c.value)) Fail(path, line, name + ": expected id scale");
      c.ids = {id};
    } else if (name == "set_sigma_v") {
      if (!(in >> c.value)) Fail(path, line, name + ": expected px");
    } else if (name == "set_constant_frame") {
      int id = 0, constant = 1;
      if (!(in >> id >> constant)) Fail(path, line, name + ": expected id 0|1");
      c.ids = {id};
      c.flag = constant != 0;
    } else if (name == "set_pose" || name == "expect") {
      int id = 0;
      if (!(in >> id)) Fail(path, line, name + ": expected id");
      c.ids = {id};
      c.a = ReadPose(in, path, line);
      if (name == "expect" && p.kind == "ba") {
        p.expect[id] = *c.a;
        continue;
      }
    } else if (name == "end") {
      ended = true;
      continue;
    } else {
      Fail(path, line, "unknown record '" + name + "'");
    }
    p.calls.push_back(std::move(c));
  }
  if (!ended) Fail(path, line, "missing 'end' (truncated file?)");
  p.window.costs = p.costs;
  return p;
}

double Seconds(Clock::time_point a, Clock::time_point b) {
  return std::chrono::duration<double>(b - a).count();
}

double MaxPoseDiff(const Vector6d& a, const Vector6d& b) { return (a - b).cwiseAbs().maxCoeff(); }

struct Stats {
  double median = 0, p95 = 0, p99 = 0, mean = 0, min = 0, max = 0;
  size_t n = 0;
};

Stats Summarise(std::vector<double> x) {
  Stats s;
  s.n = x.size();
  if (x.empty()) return s;
  std::sort(x.begin(), x.end());
  // Linear interpolation between order statistics (numpy's default percentile).
  auto pct = [&](double q) {
    const double pos = q / 100.0 * static_cast<double>(x.size() - 1);
    const size_t lo = static_cast<size_t>(std::floor(pos));
    const size_t hi = std::min(lo + 1, x.size() - 1);
    return x[lo] + (pos - static_cast<double>(lo)) * (x[hi] - x[lo]);
  };
  s.median = pct(50);
  s.p95 = pct(95);
  s.p99 = pct(99);
  s.min = x.front();
  s.max = x.back();
  double sum = 0;
  for (double v : x) sum += v;
  s.mean = sum / static_cast<double>(x.size());
  return s;
}

std::string Json(const Stats& s, double scale) {
  char buf[320];
  std::snprintf(buf, sizeof(buf),
                "{\"median\": %.6g, \"p95\": %.6g, \"p99\": %.6g, \"mean\": %.6g, \"min\": %.6g, "
                "\"max\": %.6g, \"n\": %zu}",
                s.median * scale, s.p95 * scale, s.p99 * scale, s.mean * scale, s.min * scale,
                s.max * scale, s.n);
  return buf;
}

std::string Samples(const std::vector<double>& x, double scale) {
  std::ostringstream out;
  out.precision(9);
  out << "[";
  for (size_t i = 0; i < x.size(); ++i) out << (i ? ", " : "") << x[i] * scale;
  return out.str() + "]";
}

std::string Quote(const std::string& s) {
  std::string out = "\"";
  for (char ch : s) {
    if (ch == '"' || ch == '\\') out += '\\';
    out += ch;
  }
  return out + "\"";
}

std::string RunBundle(const Problem& p, int repeats) {
  std::vector<double> build, solve_wall, solve_ceres;
  int iterations = 0, residual_blocks = 0;
  double final_cost = 0, max_diff = 0;
  std::string termination, solver;
  for (int r = 0; r < repeats; ++r) {
    const auto t0 = Clock::now();
    BundleAdjuster ba(p.K, p.costs);
    for (const Call& c : p.calls) {
      if (c.name == "add_frame") {
        ba.AddFrame(c.ids[0], *c.a, c.b, c.ratio, c.scale);
      } else if (c.name == "add_pair") {
        ba.AddPair(c.ids[0], c.ids[1], *c.points_l, *c.points_m);
      } else if (c.name == "set_plane") {
        ba.SetPlane(c.plane);
      } else if (c.name == "set_constant_frame") {
        ba.SetConstantFrame(c.ids[0], c.flag);
      } else if (c.name == "set_pose") {
        ba.SetPose(c.ids[0], *c.a);
      }
    }
    const auto t1 = Clock::now();
    const auto summary = ba.Solve();
    const auto t2 = Clock::now();
    build.push_back(Seconds(t0, t1));
    solve_wall.push_back(Seconds(t1, t2));
    solve_ceres.push_back(summary.solve_time_s);
    iterations = summary.iterations;
    residual_blocks = summary.num_residual_blocks;
    final_cost = summary.final_cost;
    termination = summary.termination;
    solver = summary.linear_solver;
    for (const auto& [id, pose] : p.expect) {
      max_diff = std::max(max_diff, MaxPoseDiff(ba.GetPose(id), pose));
    }
    if (p.expect_plane) {
      max_diff = std::max(max_diff, (ba.Plane() - *p.expect_plane).cwiseAbs().maxCoeff());
    }
  }
  std::ostringstream out;
  out << "{\"file\": " << Quote(p.path) << ", \"kind\": \"ba\", \"frames\": " << p.num_frames
      << ", \"pairs\": " << p.num_pairs << ", \"correspondences\": " << p.num_correspondences
      << ", \"use_emt\": " << (p.costs.use_emt ? "true" : "false")
      << ", \"num_threads\": " << p.costs.num_threads << ", \"repeats\": " << repeats
      << ", \"linear_solver\": " << Quote(solver) << ", \"iterations\": " << iterations
      << ", \"residual_blocks\": " << residual_blocks << ", \"final_cost\": " << final_cost
      << ", \"termination\": " << Quote(termination)
      << ",\n   \"build_s\": " << Json(Summarise(build), 1.0)
      << ",\n   \"solve_wall_s\": " << Json(Summarise(solve_wall), 1.0)
      << ",\n   \"solve_ceres_s\": " << Json(Summarise(solve_ceres), 1.0)
      << ",\n   \"samples\": {\"solve_wall_s\": " << Samples(solve_wall, 1.0)
      << ", \"solve_ceres_s\": " << Samples(solve_ceres, 1.0) << "}"
      << ",\n   \"max_abs_diff_vs_recorded\": " << max_diff << "}";
  return out.str();
}

std::string RunWindow(const Problem& p, int repeats) {
  std::vector<double> step_wall, step_cpp, step_ceres, per_frame, replay;
  double max_diff = 0;
  size_t steps = 0;
  int redos = 0;
  for (int r = 0; r < repeats; ++r) {
    const auto t_start = Clock::now();
    SlidingWindow window(p.K, p.window);
    size_t steps_here = 0;
    redos = 0;
    for (const Call& c : p.calls) {
      if (c.name == "add_frame") {
        window.AddFrame(c.ids[0], c.a, c.b, c.flag, c.ratio, c.scale);
      } else if (c.name == "add_pair") {
        window.AddPair(c.ids[0], c.ids[1], *c.points_l, *c.points_m);
      } else if (c.name == "set_plane") {
        window.SetPlane(c.plane);
      } else if (c.name == "set_emt_sigma_scale") {
        window.SetEmtSigmaScale(c.ids[0], c.value);
      } else if (c.name == "set_sigma_v") {
        window.SetSigmaV(c.value);
      } else if (c.name == "forget") {
        window.Forget(c.ids);
      } else if (c.name == "expect") {
        max_diff = std::max(max_diff, MaxPoseDiff(window.GetPose(c.ids[0]), *c.a));
      } else if (c.name == "step" || c.name == "redo") {
        const auto t0 = Clock::now();
        const auto s = c.name == "step" ? window.Step(c.ids, c.flag)
                                         : window.Redo(c.ids, c.ids2, c.flag);
        const double wall = Seconds(t0, Clock::now());
        if (c.name == "redo") {
          // A gating redo belongs to the step before it: one latency per step, as the caller
          // sees it.
          ++redos;
          step_wall.back() += wall;
          step_cpp.back() += s.step_time_s;
          step_ceres.back() += s.solve_time_s;
          per_frame.back() = step_wall.back() / static_cast<double>(s.frame_ids.size());
          continue;
        }
        ++steps_here;
        step_wall.push_back(wall);
        step_cpp.push_back(s.step_time_s);
        step_ceres.push_back(s.solve_time_s);
        per_frame.push_back(wall / static_cast<double>(std::max<size_t>(s.frame_ids.size(), 1)));
      }
    }
    replay.push_back(Seconds(t_start, Clock::now()));
    steps = steps_here;
  }
  std::ostringstream out;
  out << "{\"file\": " << Quote(p.path) << ", \"kind\": \"window\", \"frames\": " << p.num_frames
      << ", \"pairs\": " << p.num_pairs << ", \"correspondences\": " << p.num_correspondences
      << ", \"window_size\": " << p.window.window_size << ", \"num_new\": " << p.window.num_new
      << ", \"linear_solver\": " << Quote(p.costs.linear_solver)
      << ", \"num_threads\": " << p.costs.num_threads << ", \"repeats\": " << repeats
      << ", \"steps\": " << steps << ", \"redos_per_replay\": " << redos
      << ",\n   \"step_wall_ms\": " << Json(Summarise(step_wall), 1e3)
      << ",\n   \"step_cpp_ms\": " << Json(Summarise(step_cpp), 1e3)
      << ",\n   \"step_ceres_ms\": " << Json(Summarise(step_ceres), 1e3)
      << ",\n   \"per_new_frame_ms\": " << Json(Summarise(per_frame), 1e3)
      << ",\n   \"replay_s\": " << Json(Summarise(replay), 1.0)
      << ",\n   \"samples\": {\"step_wall_ms\": " << Samples(step_wall, 1e3)
      << ", \"step_cpp_ms\": " << Samples(step_cpp, 1e3)
      << ", \"per_new_frame_ms\": " << Samples(per_frame, 1e3) << "}"
      << ",\n   \"max_abs_diff_vs_recorded\": " << max_diff << "}";
  return out.str();
}

}  // namespace

int main(int argc, char** argv) {
  int repeats = 5, threads = 0;
  std::string out_path;
  std::vector<std::string> files;
  for (int i = 1; i < argc; ++i) {
    const std::string arg = argv[i];
    if ((arg == "--repeats" || arg == "--threads" || arg == "--out") && i + 1 < argc) {
      const std::string value = argv[++i];
      if (arg == "--repeats") repeats = std::stoi(value);
      if (arg == "--threads") threads = std::stoi(value);
      if (arg == "--out") out_path = value;
    } else if (arg == "-h" || arg == "--help") {
      std::cout << "usage: fusedmosaic_solver_bench [--repeats N] [--threads T] --out JSON "
                   "FILE...\n";
      return 0;
    } else {
      files.push_back(arg);
    }
  }
  if (files.empty() || repeats < 1) {
    std::cerr << "usage: fusedmosaic_solver_bench [--repeats N] [--threads T] --out JSON "
                 "FILE...\n";
    return 2;
  }
  std::vector<std::string> results;
  try {
    for (const auto& f : files) {
      Problem p = Load(f);
      if (threads > 0) {
        p.costs.num_threads = threads;
        p.window.costs.num_threads = threads;
      }
      const auto t0 = Clock::now();
      results.push_back(p.kind == "ba" ? RunBundle(p, repeats) : RunWindow(p, repeats));
      std::cerr << f << ": " << Seconds(t0, Clock::now()) << " s\n";
    }
  } catch (const std::exception& e) {
    std::cerr << "error: " << e.what() << "\n";
    return 1;
  }
  std::ostringstream json;
  json << "{\"program\": \"fusedmosaic_solver_bench\", \"timer\": \"std::chrono::steady_clock\", "
       << "\"results\": [\n  ";
  for (size_t i = 0; i < results.size(); ++i) json << (i ? ",\n  " : "") << results[i];
  json << "\n]}\n";
  if (out_path.empty()) {
    std::cout << json.str();
  } else {
    std::ofstream(out_path) << json.str();
  }
  return 0;
}
