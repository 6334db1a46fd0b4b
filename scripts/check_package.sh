#!/usr/bin/env bash
# Checks gs360's .deb and its install rules, without installing anything into this system:
#   scripts/check_package.sh BUILD_DIR [DEB]
# Without DEB, builds the package from BUILD_DIR with CPack first (into a temporary folder).
# Then: the package's name, control fields (dependencies from the binaries, the conffile, the
# maintainer scripts), its file list; extracted into a throwaway root: `gs360d --version` (the
# version and the build's commit), `gs360 --help`, `import gs360` from the installed module, the
# default configuration read by the installed gs360d and equal to the defaults, and
# `systemd-analyze verify` of the installed unit; lintian, when installed (scripts/setup.sh test
# installs it), with no error or warning; and `cmake --install`
# into a prefix other than /usr. Exit 0 when every check holds; the first failure is printed.
set -euo pipefail

build=$(cd "${1:?usage: check_package.sh BUILD_DIR [DEB]}" && pwd)
here=$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)
tmp=$(mktemp -d)
trap 'rm -rf "$tmp"' EXIT
fail() { echo "FAIL: $*" >&2; exit 1; }
log() { echo "check_package: $*"; }

version=$(sed -n 's/^CMAKE_PROJECT_VERSION:STATIC=//p' "$build/CMakeCache.txt")
[ -n "$version" ] || fail "no project version in $build/CMakeCache.txt"
arch=$(dpkg --print-architecture)
if [ $# -ge 2 ]; then
  deb=$2
else
  log "cpack in $build"
  cpack --config "$build/CPackConfig.cmake" -B "$tmp/out" > "$tmp/cpack.log" 2>&1 ||
    { cat "$tmp/cpack.log" >&2; fail "cpack failed"; }
  deb="$tmp/out/gs360_${version}_${arch}.deb"
fi
[ -f "$deb" ] || fail "no package $deb (expected gs360_<version>_<arch>.deb)"
log "package $(basename "$deb"), $(du -k "$deb" | cut -f1) kB"

# Control fields and the maintainer scripts.
[ "$(dpkg-deb -f "$deb" Package)" = gs360 ] || fail "Package is not gs360"
[ "$(dpkg-deb -f "$deb" Version)" = "$version" ] || fail "Version is not $version"
depends=$(dpkg-deb -f "$deb" Depends)
for dep in adduser libc6 libsqlite3 libopencv libserialport libmicrohttpd libsystemd0; do
  grep -q "$dep" <<< "$depends" || fail "Depends lacks $dep (shlibdeps?): $depends"
done
mkdir "$tmp/control"
dpkg-deb -e "$deb" "$tmp/control"
grep -qx /etc/gs360/gs360d.toml "$tmp/control/conffiles" ||
  fail "/etc/gs360/gs360d.toml is not a conffile"
for script in postinst prerm postrm; do
  [ -x "$tmp/control/$script" ] || fail "no executable $script"
  sh -n "$tmp/control/$script" || fail "$script is not valid sh"
done
grep -q "adduser --system" "$tmp/control/postinst" || fail "postinst adds no system user"

# The file list: what must be there, and nothing outside /usr, /etc and /lib.
dpkg-deb -c "$deb" | awk '{print $6}' | sed 's|^\./|/|' > "$tmp/files"
for f in /usr/bin/gs360 /usr/bin/gs360d /etc/gs360/gs360d.toml /lib/systemd/system/gs360d.service \
  /usr/share/man/man1/gs360.1.gz /usr/share/man/man1/gs360d.1.gz \
  /usr/share/doc/gs360/copyright /usr/share/doc/gs360/changelog.gz \
  /usr/share/doc/gs360/README.md /usr/share/doc/gs360/daemon.md /usr/share/doc/gs360/api.md; do
  grep -qx "$f" "$tmp/files" || fail "the package has no $f"
done
grep -q '^/usr/lib/python3/dist-packages/gs360\..*\.so$' "$tmp/files" ||
  fail "the package has no Python module in /usr/lib/python3/dist-packages"
if grep -v -E '^/(usr|etc|lib)(/|$)|^/$' "$tmp/files"; then fail "files outside /usr, /etc, /lib"; fi
if grep -E '^/usr/local|^/usr/etc' "$tmp/files"; then fail "files under /usr/local or /usr/etc"; fi

# The extracted root: the programs, the module, the configuration, the unit.
root="$tmp/root"
dpkg-deb -x "$deb" "$root"
line=$("$root/usr/bin/gs360d" --version)
commit=$(sed -n 's/.*Commit() { return "\(.*\)"; }/\1/p' "$build/base/version_info.cc")
[ "$line" = "gs360d $version (commit $commit)" ] || fail "gs360d --version: '$line', commit $commit"
[[ "$commit" =~ ^([0-9a-f]{12}(-dirty)?|unknown)$ ]] || fail "commit '$commit'"
# (Outputs are captured first: `grep -q` in a pipe may close it early, and pipefail fails then.)
[ "$("$root/usr/bin/gs360" --version)" = "gs360 $version (commit $commit)" ] || fail "gs360 --version"
help=$("$root/usr/bin/gs360" --help) || fail "gs360 --help failed"
grep -q "demo" <<< "$help" || fail "gs360 --help lists no demo"
log "$line"
python=/usr/bin/python3
"$python" -c 'import sys; sys.exit(0 if "/usr/lib/python3/dist-packages" in sys.path else 1)' ||
  fail "/usr/lib/python3/dist-packages is not on $python's sys.path"
got=$(PYTHONPATH="$root/usr/lib/python3/dist-packages" "$python" -c \
  'import gs360; print(gs360.__version__, gs360.__commit__, gs360.__file__)')
[[ "$got" == "$version $commit $root/usr/lib/python3/dist-packages/gs360."* ]] ||
  fail "import gs360 from the package: $got"
log "import gs360: $got"

# The default configuration is read by the installed gs360d, and every value its comments give is
# the default: uncommenting them all changes nothing.
conf="$root/etc/gs360/gs360d.toml"
"$root/usr/bin/gs360d" --config "$conf" --print-config > "$tmp/as_shipped.toml" ||
  fail "the installed gs360d refuses the installed $conf"
grep -qx "data_dir = '/var/lib/gs360'" "$tmp/as_shipped.toml" || fail "data_dir is not /var/lib/gs360"
sed -E 's/^# ?(\[[a-z_.]+\]|[a-z_]+ = )/\1/' "$conf" > "$tmp/uncommented.toml"
"$root/usr/bin/gs360d" --config "$tmp/uncommented.toml" --print-config > "$tmp/uncommented_out.toml" ||
  fail "$conf with its examples uncommented is refused"
diff "$tmp/as_shipped.toml" "$tmp/uncommented_out.toml" > "$tmp/conf.diff" ||
  { cat "$tmp/conf.diff" >&2; fail "a value in $conf's comments is not the default"; }

unit="$root/lib/systemd/system/gs360d.service"
grep -qx "ExecStart=/usr/bin/gs360d --config /etc/gs360/gs360d.toml" "$unit" || fail "ExecStart in $unit"
if command -v systemd-analyze > /dev/null; then
  # Verified in the extracted root with the system's own targets beside it (the unit's default
  # dependencies, sysinit.target and the like, are systemd's, not the package's); its
  # Documentation= man page is checked below, since `verify` looks for it in this system's manpath.
  cp -n /lib/systemd/system/*.target "$root/lib/systemd/system/"
  systemd-analyze verify --man=no --root="$root" /lib/systemd/system/gs360d.service \
    > "$tmp/verify.log" 2>&1 ||
    { cat "$tmp/verify.log" >&2; fail "systemd-analyze verify"; }
  if [ -s "$tmp/verify.log" ]; then cat "$tmp/verify.log" >&2; fail "systemd-analyze verify warned"; fi
  log "systemd-analyze verify: clean"
else
  fail "systemd-analyze is not installed"
fi

for page in gs360 gs360d; do
  man -l "$root/usr/share/man/man1/$page.1.gz" > "$tmp/man.txt" 2> "$tmp/man.log"
  grep -q "^NAME" "$tmp/man.txt" ||
    { cat "$tmp/man.log" >&2; fail "man page $page(1) does not render"; }
  if [ -s "$tmp/man.log" ]; then cat "$tmp/man.log" >&2; fail "man page $page(1) has warnings"; fi
done

if command -v lintian > /dev/null; then
  lintian --fail-on error,warning --tag-display-limit 0 "$deb" > "$tmp/lintian.log" 2>&1 ||
    { cat "$tmp/lintian.log" >&2; fail "lintian"; }
  log "lintian: $(grep -c . "$tmp/lintian.log" || true) lines ($(tr '\n' ';' < "$tmp/lintian.log"))"
else
  log "lintian not installed: skipped (scripts/setup.sh test installs it)"
fi

# cmake --install into another prefix: the configuration, the unit and the module under it.
prefix="$tmp/prefix"
cmake --install "$build" --prefix "$prefix" > /dev/null || fail "cmake --install --prefix"
[ -f "$prefix/etc/gs360/gs360d.toml" ] || fail "cmake --install: no PREFIX/etc/gs360/gs360d.toml"
grep -qx "ExecStart=$prefix/bin/gs360d --config $prefix/etc/gs360/gs360d.toml" \
  "$prefix/lib/systemd/system/gs360d.service" || fail "cmake --install: the unit's ExecStart"
ls "$prefix"/lib/python3.*/dist-packages/gs360.*.so > /dev/null || fail "cmake --install: no module"
log "every check holds"
