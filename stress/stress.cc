#include "stress/stress.h"

#include <algorithm>
#include <chrono>
#include <cstdarg>
#include <cstdio>
#include <exception>
#include <stdexcept>
#include <string>

#include <nlohmann/json.hpp>

#include "stress/stress_cases.h"

namespace gs360 {

namespace stress {

std::string Format(const char* format, ...) {
  va_list args;
  va_start(args, format);
  va_list copy;
  va_copy(copy, args);
  const int n = std::vsnprintf(nullptr, 0, format, copy);
  va_end(copy);
  std::string out(static_cast<std::size_t>(n > 0 ? n : 0), '\0');
  if (n > 0) std::vsnprintf(out.data(), out.size() + 1, format, args);
  va_end(args);
  return out;
}

}  // namespace stress

void StressContext::Check() const {
  if (threads < 1 || threads > 64) {
    throw std::invalid_argument("StressContext.threads = " + std::to_string(threads) +
                                ": expected 1..64");
  }
}

std::vector<StressCase> StressCases() {
  std::vector<StressCase> all;
  for (auto cases : {stress::PoseCases(), stress::IntrinsicsCases(), stress::FrameCases(),
                     stress::IntegrationCases(), stress::GeometryCases(), stress::MlpCases()}) {
    for (StressCase& c : cases) all.push_back(std::move(c));
  }
  return all;
}

StressOutcome RunStressCase(const StressCase& c, const StressContext& context) {
  StressOutcome out;
  out.stage = c.stage;
  out.name = c.name;
  out.expected = c.expected;
  out.limit = c.limit;
  const auto start = std::chrono::steady_clock::now();
  try {
    out.passed = c.run(context, &out.observed);
  } catch (const std::exception& e) {
    // A case that expects an error catches it itself; anything reaching here was not expected.
    out.passed = false;
    out.observed = std::string("unexpected exception: ") + e.what();
  }
  out.seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
  return out;
}

std::vector<StressOutcome> RunStress(const StressContext& context,
                                     const std::vector<std::string>& only,
                                     const std::function<void(const StressOutcome&)>& progress) {
  context.Check();
  std::vector<StressOutcome> outcomes;
  for (const StressCase& c : StressCases()) {
    const bool wanted = only.empty() ||
                        std::find(only.begin(), only.end(), c.stage) != only.end() ||
                        std::find(only.begin(), only.end(), c.name) != only.end();
    if (!wanted) continue;
    outcomes.push_back(RunStressCase(c, context));
    if (progress) progress(outcomes.back());
  }
  return outcomes;
}

nlohmann::json StressOutcomesToJson(const std::vector<StressOutcome>& outcomes) {
  nlohmann::json cases = nlohmann::json::array();
  int failed = 0;
  for (const StressOutcome& o : outcomes) {
    failed += o.passed ? 0 : 1;
    cases.push_back({{"stage", o.stage},
                     {"name", o.name},
                     {"expected", o.expected},
                     {"observed", o.observed},
                     {"passed", o.passed},
                     {"limit", o.limit},
                     {"seconds", o.seconds}});
  }
  return {
      {"cases", cases}, {"passed", static_cast<int>(outcomes.size()) - failed}, {"failed", failed}};
}

namespace {

// A table cell: pipes escaped, line breaks as spaces.
std::string Cell(std::string s) {
  std::string out;
  for (char ch : s) {
    if (ch == '|') {
      out += "\\|";
    } else if (ch == '\n') {
      out += ' ';
    } else {
      out += ch;
    }
  }
  return out;
}

}  // namespace

std::string StressOutcomesToMarkdown(const std::vector<StressOutcome>& outcomes) {
  std::string md = "| stage | case | expected | observed | result |\n|---|---|---|---|---|\n";
  for (const StressOutcome& o : outcomes) {
    md += "| " + Cell(o.stage) + " | " + Cell(o.name) + " | " + Cell(o.expected) + " | " +
          Cell(o.observed) + " | " +
          (!o.passed ? "**FAIL**"
           : o.limit ? "limit"
                     : "pass") +
          " |\n";
  }
  return md;
}

}  // namespace gs360
