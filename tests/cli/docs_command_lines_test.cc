// docs/cli.md's command table against the real gs360: every command line it documents is a
// command of the executable, every option it names is one of that command's, and a command that
// takes a run reads a number as the run (it reaches for the daemon, exit code 5 with none there,
// rather than refusing its arguments).

#include <catch2/catch.hpp>

#include <cctype>
#include <fstream>
#include <regex>
#include <set>
#include <sstream>
#include <string>
#include <vector>

#include "tests/cli/run_gs360.h"

namespace {

using gs360::test::Gs360;

// One documented command line: its command words ("run start"), the options it names, and the
// options given outside brackets (required), with the text of their values.
struct DocumentedLine {
  std::string text;
  std::string words;
  std::vector<std::string> options;
  std::vector<std::string> required;
  bool takes_run = false;
};

std::vector<std::string> DocTokens(const std::string& s) {
  std::istringstream in(s);
  std::vector<std::string> out;
  for (std::string t; in >> t;) out.push_back(t);
  return out;
}

bool DocIsCommandWord(const std::string& t) {
  if (t.empty()) return false;
  for (char c : t) {
    if (!std::islower(static_cast<unsigned char>(c)) && c != '-') return false;
  }
  return t[0] != '-';
}

DocumentedLine ParseDocLine(const std::string& text) {
  DocumentedLine line;
  line.text = text;
  const std::vector<std::string> tokens = DocTokens(text);
  std::size_t i = 0;
  for (; i < tokens.size() && DocIsCommandWord(tokens[i]); ++i) {
    line.words += (line.words.empty() ? "" : " ") + tokens[i];
  }
  int depth = 0;
  for (; i < tokens.size(); ++i) {
    const std::string& t = tokens[i];
    if (depth == 0 && t == "RUN") line.takes_run = true;
    if (depth == 0 && t.rfind("--", 0) == 0) line.required.push_back(t);
    for (char c : t) depth += c == '[' || c == '(' ? 1 : (c == ']' || c == ')' ? -1 : 0);
  }
  const std::regex option("--[a-z][a-z-]*");
  for (std::sregex_iterator m(text.begin(), text.end(), option), end; m != end; ++m) {
    line.options.push_back(m->str());
  }
  return line;
}

// The backticked command lines of the first column of the command table.
std::vector<DocumentedLine> DocumentedLines() {
  std::ifstream in(std::string(GS360_SOURCE_DIR) + "/docs/cli.md");
  REQUIRE(in);
  std::vector<DocumentedLine> lines;
  bool in_table = false;
  for (std::string row; std::getline(in, row);) {
    if (row.rfind("| command | what |", 0) == 0) {
      in_table = true;
      continue;
    }
    if (!in_table) continue;
    if (row.rfind("|", 0) != 0) break;
    if (row.rfind("|---", 0) == 0) continue;
    const std::size_t end = row.find(" | ", 2);
    REQUIRE(end != std::string::npos);
    std::string cell = row.substr(2, end - 2);
    // "\|" in a cell is a table-escaped "|" (a choice).
    for (std::size_t p; (p = cell.find("\\|")) != std::string::npos;) cell.replace(p, 2, "|");
    const std::regex code("`([^`]+)`");
    for (std::sregex_iterator m(cell.begin(), cell.end(), code), stop; m != stop; ++m) {
      lines.push_back(ParseDocLine((*m)[1].str()));
    }
  }
  return lines;
}

}  // namespace

TEST_CASE("docs/cli.md: every documented command and option is the executable's", "[cli][docs]") {
  const std::vector<DocumentedLine> lines = DocumentedLines();
  REQUIRE(lines.size() >= 20);
  std::set<std::string> commands;
  for (const DocumentedLine& line : lines) {
    INFO("documented: " << line.text);
    REQUIRE_FALSE(line.words.empty());
    commands.insert(line.words);
    const auto help = Gs360(line.words + " --help");
    INFO(help.out);
    CHECK(help.status == 0);
    for (const std::string& option : line.options) {
      INFO("option " << option);
      CHECK(help.out.find(option) != std::string::npos);
    }
  }
  // The table names the commands of every family.
  for (const char* c :
       {"run start", "run list", "calibrate", "export", "demo", "recon", "bench heldout"}) {
    CHECK(commands.count(c) == 1);
  }
  const auto top = Gs360("--help");
  for (const char* global : {"--daemon", "--token", "--json", "-v"}) {
    INFO(global << " in: " << top.out);
    CHECK(top.out.find(global) != std::string::npos);
  }
}

TEST_CASE("docs/cli.md: a documented command line on a run reads a number as the run",
          "[cli][docs]") {
  // Nothing listens on port 9 of the loopback: a command line that parses asks the daemon there
  // and gets exit code 5 ("no daemon answers"); one that does not parse exits 2 before that.
  const std::string no_daemon = " --daemon http://127.0.0.1:9";
  int tried = 0;
  for (const DocumentedLine& line : DocumentedLines()) {
    if (!line.takes_run) continue;
    bool local = false;
    std::string args = line.words + " 7";
    for (const std::string& option : line.required) {
      if (option == "--db") local = true;  // a database file, no daemon
      args += " " + option + " /tmp/gs360-docs-test-out";
    }
    if (local) continue;
    INFO("documented: " << line.text << "\nran: gs360 " << args);
    auto r = Gs360(args + no_daemon);
    INFO(r.out);
    CHECK(r.status == 5);
    ++tried;
    if (line.text.find("--confirm position|sensor") != std::string::npos) {
      r = Gs360(args + " --confirm position" + no_daemon);
      INFO(r.out);
      CHECK(r.status == 5);
    }
  }
  CHECK(tried >= 8);
}
