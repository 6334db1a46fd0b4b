// The host side of Marlin's line protocol (gcode/marlin_stream.h) against a printer that checks
// every line's number and checksum as Marlin does: garbled lines, lost lines and lost oks.

#include <catch2/catch.hpp>

#include <random>
#include <string>
#include <vector>

#include "gcode/marlin_messages.h"
#include "gcode/marlin_stream.h"

namespace {

using gs360::MarlinStream;
using Kind = gs360::MarlinStreamEvent::Kind;

// What Marlin does with a line from the host (queue.cpp's rules): a checksum that does not match,
// or a number that is not the last + 1 (M110 aside, which sets it), is refused with an error, a
// Resend of the line it expects, and an ok; a good line runs and gets its ok.
struct CheckingPrinter {
  long last = -1;  // no line yet: only an M110 is taken
  std::vector<std::string> ran;

  std::vector<std::string> Refuse(const std::string& why) const {
    return {"Error:" + why + ", Last Line: " + std::to_string(last),
            "Resend: " + std::to_string(last + 1), "ok"};
  }
  std::vector<std::string> Take(const std::string& line) {
    const auto star = line.rfind('*');
    if (star == std::string::npos || line[0] != 'N') return Refuse("No Checksum with line number");
    if (std::to_string(gs360::MarlinChecksum(line.substr(0, star))) != line.substr(star + 1)) {
      return Refuse("checksum mismatch");
    }
    const auto space = line.find(' ');
    const long number = std::stol(line.substr(1, space - 1));
    const std::string command = line.substr(space + 1, star - space - 1);
    if (command.rfind("M110", 0) == 0) {
      last = number;
      return {"ok"};
    }
    if (number != last + 1) return Refuse("Line Number is not Last Line Number+1");
    last = number;
    ran.push_back(command);
    return {"ok"};
  }
};

// Feeds the printer's replies to the stream; the events, in order.
std::vector<gs360::MarlinStreamEvent> Answer(MarlinStream& stream,
                                             const std::vector<std::string>& replies) {
  std::vector<gs360::MarlinStreamEvent> events;
  for (const std::string& r : replies) events.push_back(stream.OnReply(gs360::ParseMarlinLine(r)));
  return events;
}

}  // namespace

TEST_CASE("MarlinStream: numbering starts with M110, a line at a time, each acknowledged",
          "[gcode][marlin]") {
  MarlinStream s;
  CHECK(s.Idle());
  CHECK(s.NextToWrite() == "N0 M110 N0*125");
  CHECK_FALSE(s.NextToWrite());  // waits for its ok
  CHECK(Answer(s, {"ok"})[0].kind == Kind::kNone);
  const auto home = s.Queue("G28 ; home");
  const auto move = s.Queue("G1 Z5 F300");
  CHECK(s.Queued() == 2);
  CHECK(s.NextToWrite() == gs360::MarlinFrame(1, "G28"));
  CHECK_FALSE(s.NextToWrite());
  auto e = Answer(s, {"echo:busy: processing", "ok"});
  CHECK(e[0].kind == Kind::kBusy);
  CHECK(e[1].kind == Kind::kAcked);
  CHECK(e[1].sequence == home);
  CHECK(s.NextToWrite() == gs360::MarlinFrame(2, "G1 Z5 F300"));
  e = Answer(s, {"X:0.00 Y:0.00 Z:5.00 E:0.00 Count X:0 Y:0 Z:2000", "ok"});
  CHECK(e[0].kind == Kind::kNone);
  CHECK(e[1].sequence == move);
  CHECK(s.Idle());
  CHECK_THROWS_AS(s.Queue("G1 X1*3"), std::invalid_argument);
  CHECK(s.Queued() == 0);
}

TEST_CASE("MarlinStream: a garbled line is written again, a lost ok is found by its number",
          "[gcode][marlin]") {
  MarlinStream s;
  CheckingPrinter printer;
  Answer(s, printer.Take(*s.NextToWrite()));
  const auto first = s.Queue("G1 X10");
  SECTION("garbled on the way: refused, asked for again, its refusal's ok not taken for its own") {
    std::string line = *s.NextToWrite();
    line[4] = 'Y';
    const auto e = Answer(s, printer.Take(line));
    CHECK(e[1].kind == Kind::kResend);
    CHECK(e[2].kind == Kind::kNone);  // the ok of the refusal
    CHECK(s.Resends() == 1);
    const auto again = Answer(s, printer.Take(*s.NextToWrite()));
    CHECK(again[0].kind == Kind::kAcked);
    CHECK(again[0].sequence == first);
  }
  SECTION("the ok lost: written again, refused as a duplicate, which says it was taken") {
    printer.Take(*s.NextToWrite());  // taken, its ok never arrives
    CHECK_FALSE(s.NextToWrite());
    const auto e = Answer(s, printer.Take(*s.RetryInFlight()));
    CHECK(e[1].kind == Kind::kAcked);
    CHECK(e[1].sequence == first);
    CHECK(e[2].kind == Kind::kNone);
    CHECK(s.Retries() == 1);
  }
  SECTION("the line lost: written again and taken") {
    (void)s.NextToWrite();  // never arrives
    const auto e = Answer(s, printer.Take(*s.RetryInFlight()));
    CHECK(e[0].kind == Kind::kAcked);
  }
  CHECK(printer.ran == std::vector<std::string>{"G1 X10"});
  CHECK(s.Idle());
}

TEST_CASE("MarlinStream: under random garbling and losses every line runs once, in order",
          "[gcode][marlin]") {
  const unsigned seed = GENERATE(1u, 2u, 3u);
  std::mt19937 rng(seed);
  std::uniform_real_distribution<double> u(0.0, 1.0);
  MarlinStream s;
  CheckingPrinter printer;
  std::vector<std::string> sent;
  for (int i = 0; i < 400; ++i) {
    sent.push_back("G1 X" + std::to_string(i % 50) + " Y" + std::to_string(i / 50) + " F3000");
    s.Queue(sent.back());
  }
  int steps = 0;
  while (!s.Idle() && ++steps < 10000) {
    std::optional<std::string> line = s.NextToWrite();
    if (!line) line = s.RetryInFlight();  // no reply in time
    REQUIRE(line);
    const double fault = u(rng);
    if (fault < 0.05) continue;            // the line lost on the way
    if (fault < 0.15) (*line)[2] ^= 0x01;  // a bit flipped
    std::vector<std::string> replies = printer.Take(*line);
    if (u(rng) < 0.05 && !replies.empty()) replies.pop_back();  // an ok lost
    for (const auto& e : Answer(s, replies)) REQUIRE(e.kind != Kind::kError);
  }
  CHECK(printer.ran == sent);
  CHECK(s.Resends() > 20);
  CHECK(s.Retries() > 20);
}

TEST_CASE("MarlinStream: a reboot drops the line in flight, a halt stops the stream",
          "[gcode][marlin]") {
  MarlinStream s;
  CheckingPrinter printer;
  Answer(s, printer.Take(*s.NextToWrite()));
  const auto press = s.Queue("G1 Z-1 F300");
  s.Queue("M400");
  printer.Take(*s.NextToWrite());
  auto e = Answer(s, {"start", "echo:Marlin 2.1.2"});
  CHECK(e[0].kind == Kind::kRebooted);
  CHECK(e[0].sequence == press);  // it may or may not have run: the caller's to find out
  s.ClearQueue();
  CHECK(s.Queued() == 0);
  CHECK(s.NextToWrite() == "N0 M110 N0*125");  // numbering again, first
  Answer(s, {"ok"});
  CHECK(s.Idle());

  s.Queue("G1 X1");
  (void)s.NextToWrite();
  e = Answer(s, {"Error:Printer halted. kill() called!"});
  CHECK(e[0].kind == Kind::kHalted);
  CHECK(s.Halted());
  CHECK_FALSE(s.NextToWrite());
  CHECK_FALSE(s.RetryInFlight());
  // A Resend for a line never sent is the numbering out of step, said as such.
  MarlinStream t;
  Answer(t, {"ok"});  // nothing written yet: a stray ok
  (void)t.NextToWrite();
  Answer(t, {"ok"});
  e = Answer(t, {"Resend: 7"});
  CHECK(e[0].kind == Kind::kError);
  CHECK_THAT(e[0].text, Catch::Contains("out of step"));
  // The refusal's ok is swallowed; the next is no line's either.
  CHECK(Answer(t, {"ok", "ok"})[1].kind == Kind::kNone);
  CHECK(t.StrayOks() == 2);
}
