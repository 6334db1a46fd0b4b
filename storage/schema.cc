#include "storage/schema.h"

#include <array>

namespace gs360 {
namespace {

// Large blobs are the last column of their row: SQLite stores a row's columns in order, so
// columns after a blob would need its whole overflow chain read.
constexpr std::string_view kVersion1 = R"sql(
CREATE TABLE runs (
  id            INTEGER PRIMARY KEY,
  name          TEXT NOT NULL DEFAULT '',
  config_json   TEXT NOT NULL,
  mesh_hash     TEXT NOT NULL,
  state         TEXT NOT NULL DEFAULT 'created' CHECK (state IN
                  ('created', 'running', 'paused', 'interrupted', 'done', 'failed', 'cancelled')),
  created_at    REAL NOT NULL,
  started_at    REAL,
  updated_at    REAL NOT NULL,
  finished_at   REAL,
  running_since REAL,
  active_s      REAL NOT NULL DEFAULT 0
);

CREATE TABLE probes (
  id          INTEGER PRIMARY KEY,
  run_id      INTEGER NOT NULL REFERENCES runs(id) ON DELETE CASCADE,
  plan_index  INTEGER NOT NULL CHECK (plan_index >= 0),
  point_x     REAL NOT NULL, point_y    REAL NOT NULL, point_z    REAL NOT NULL,
  normal_x    REAL NOT NULL, normal_y   REAL NOT NULL, normal_z   REAL NOT NULL,
  approach_x  REAL NOT NULL, approach_y REAL NOT NULL, approach_z REAL NOT NULL,
  press_x     REAL NOT NULL, press_y    REAL NOT NULL, press_z    REAL NOT NULL,
  retract_x   REAL NOT NULL, retract_y  REAL NOT NULL, retract_z  REAL NOT NULL,
  state       TEXT NOT NULL DEFAULT 'planned'
                CHECK (state IN ('planned', 'captured', 'failed', 'skipped')),
  attempts    INTEGER NOT NULL DEFAULT 0 CHECK (attempts >= 0),
  mpos_x      REAL, mpos_y REAL, mpos_z REAL,
  sync_time   REAL,
  captured_at REAL,
  last_error  TEXT,
  skip_reason TEXT,
  UNIQUE (run_id, plan_index),
  CHECK (state <> 'captured' OR (mpos_x IS NOT NULL AND mpos_y IS NOT NULL AND
         mpos_z IS NOT NULL AND sync_time IS NOT NULL AND captured_at IS NOT NULL AND
         attempts >= 1))
);
CREATE INDEX probes_by_state ON probes (run_id, state, plan_index);

CREATE TABLE frames (
  id         INTEGER PRIMARY KEY,
  run_id     INTEGER NOT NULL REFERENCES runs(id) ON DELETE CASCADE,
  probe_id   INTEGER REFERENCES probes(id) ON DELETE CASCADE,
  kind       TEXT NOT NULL CHECK (kind IN ('press', 'reference')),
  timestamp  REAL NOT NULL,
  width      INTEGER NOT NULL CHECK (width > 0),
  height     INTEGER NOT NULL CHECK (height > 0),
  channels   INTEGER NOT NULL CHECK (channels IN (1, 3)),
  bit_depth  INTEGER NOT NULL CHECK (bit_depth IN (8, 16)),
  size       INTEGER NOT NULL,
  checksum   TEXT NOT NULL,
  png        BLOB NOT NULL,
  CHECK ((kind = 'press') = (probe_id IS NOT NULL))
);
CREATE UNIQUE INDEX frames_one_per_probe ON frames (probe_id) WHERE probe_id IS NOT NULL;
CREATE INDEX frames_by_kind_time ON frames (run_id, kind, timestamp);
CREATE INDEX frames_by_run ON frames (run_id);

CREATE TABLE events (
  id        INTEGER PRIMARY KEY,
  run_id    INTEGER REFERENCES runs(id) ON DELETE CASCADE,
  timestamp REAL NOT NULL,
  level     TEXT NOT NULL CHECK (level IN ('debug', 'info', 'warning', 'error')),
  message   TEXT NOT NULL,
  data_json TEXT
);
CREATE INDEX events_by_run ON events (run_id, id);
)sql";

constexpr std::string_view kVersion2 = R"sql(
CREATE TABLE artifacts (
  id           INTEGER PRIMARY KEY,
  run_id       INTEGER NOT NULL REFERENCES runs(id) ON DELETE CASCADE,
  stage        TEXT NOT NULL,
  input_hash   TEXT NOT NULL,
  created_at   REAL NOT NULL,
  metrics_json TEXT NOT NULL DEFAULT '{}',
  size         INTEGER NOT NULL,
  checksum     TEXT NOT NULL,
  blob         BLOB NOT NULL,
  UNIQUE (run_id, stage, input_hash)
);

CREATE TABLE models (
  id            INTEGER PRIMARY KEY,
  run_id        INTEGER REFERENCES runs(id) ON DELETE SET NULL,
  name          TEXT NOT NULL,
  version       TEXT NOT NULL,
  created_at    REAL NOT NULL,
  metadata_json TEXT NOT NULL DEFAULT '{}',
  size          INTEGER NOT NULL,
  checksum      TEXT NOT NULL,
  blob          BLOB NOT NULL,
  UNIQUE (name, version)
);
)sql";

// The reason the run last stopped short (an alarm, a failed set-up), for the API's last_error;
// what it waits for the user to confirm before it goes on; the path of the last motion it sent
// (the controller must stand on it when a run resumes); and deleted runs kept as a tombstone
// row, so that a run id is never given out twice.
constexpr std::string_view kVersion3 = R"sql(
ALTER TABLE runs ADD COLUMN last_error TEXT NOT NULL DEFAULT '';
ALTER TABLE runs ADD COLUMN deleted_at REAL;
ALTER TABLE runs ADD COLUMN awaiting TEXT NOT NULL DEFAULT '';
ALTER TABLE runs ADD COLUMN commanded_path TEXT NOT NULL DEFAULT '';
)sql";

// A homing cycle sent after the commanded path: the controller may stand anywhere on its way
// home, or at home, when the next session looks.
constexpr std::string_view kVersion4 = R"sql(
ALTER TABLE runs ADD COLUMN homing_sent INTEGER NOT NULL DEFAULT 0;
)sql";

// A failed probe that is not pressed again, whatever its attempts: it failed for a reason a
// second press cannot change (no impression where the plan put it).
constexpr std::string_view kVersion5 = R"sql(
ALTER TABLE probes ADD COLUMN retry INTEGER NOT NULL DEFAULT 1;
)sql";

constexpr std::array<SchemaMigration, kSchemaVersion> kMigrations = {{
    {1, kVersion1},
    {2, kVersion2},
    {3, kVersion3},
    {4, kVersion4},
    {5, kVersion5},
}};

}  // namespace

std::span<const SchemaMigration> Migrations() {
  return kMigrations;
}

}  // namespace gs360
