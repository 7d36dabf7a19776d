# Every target CI needs is here; `.ci/run` calls `make ci`.
CARGO ?= cargo
NJ130 := robots/comau_nj130/robot.dh.toml

.PHONY: build run test test-fast test-deps test-tools check fmt clippy doc snapshots bench bench-peers bench-diagnose paper calibration pose-selection stop-and-measure ci fuzz rapidchecker

build:
	$(CARGO) build --release --locked

# The main job: the error-sensitive program for the bundled NJ-130 cell (the paper's fixture).
run: build
	target/release/edbbgen $(NJ130) --fixture 258,1468,708 -o nj130.nc

# ---- What the tests run besides cargo: installed by `make test` itself -----------------------
# Each step checks first and installs only what is missing, so on a machine that has it all
# `make test-deps` takes well under a second.
#
# Debian packages: linuxcnc-uspace (LinuxCNC's rs274 interpreter reads every ngc program; its
# simulated machine runs them, tests/linuxcnc.rs), chromium (renders every HTML report,
# tests/report.rs), python3-venv (the RAPID checker's venv below). Through apt-get, as root or
# with sudo; elsewhere the missing packages are named and the target fails.
SUDO := $(shell [ "$$(id -u)" = 0 ] || echo sudo)
APT := $(SUDO) env DEBIAN_FRONTEND=noninteractive apt-get
test-tools:
	@missing=""; \
	{ command -v rs274 && command -v linuxcnc && command -v halcmd; } >/dev/null 2>&1 \
	  || missing="$$missing linuxcnc-uspace"; \
	{ command -v chromium || command -v chromium-browser || command -v google-chrome; } >/dev/null 2>&1 \
	  || missing="$$missing chromium"; \
	python3 -c "import ensurepip, venv" >/dev/null 2>&1 || missing="$$missing python3 python3-venv"; \
	[ -x /usr/bin/python3 ] || missing="$$missing python3"; \
	if [ -n "$$missing" ]; then \
	  command -v apt-get >/dev/null 2>&1 \
	    || { echo "make test-tools: the tests need (Debian package names):$$missing" >&2; exit 1; }; \
	  echo "make test-tools: installing$$missing (apt-get)"; \
	  $(APT) update -qq && $(APT) install -y -qq --no-install-recommends $$missing >/dev/null; \
	fi

# ABB's RAPID grammar checker (PyPI: rapidchecker) in a venv under target/, where the tests look
# for it (tests/dialects.rs; in CI a missing checker fails the test).
RAPIDCHECKER_VENV := target/rapidchecker-venv
rapidchecker: test-tools
	@test -x $(RAPIDCHECKER_VENV)/bin/python || python3 -m venv $(RAPIDCHECKER_VENV)
	@$(RAPIDCHECKER_VENV)/bin/python -c "import rapidchecker" 2>/dev/null || $(RAPIDCHECKER_VENV)/bin/pip install -q rapidchecker==0.1.5

test-deps: test-tools rapidchecker

# ---- The tests: one test binary, two tiers --------------------------------------------------
# `make test` (the README's command; CI) runs everything: the unit tests, every integration test
# of tests/main.rs with the slow tier included (`-- --include-ignored`), the doc tests (from a
# fresh clone under /tmp, niced, load 6-7: 20.6 min to build with the third-party crates already
# built, 13.3 min to test). One slow test alone: `cargo test --test main NAME -- --include-ignored`.
# `make test-fast` (the loop to wait for: 92 s wall from a warm build at load 7.5 on the 2
# cores, 44 s CPU) runs the unit tests and the fast integration tests. It is plain
# `cargo test`: each slow test carries `#[ignore = "slow tier: `make test` runs it"]`.
#
# The split is by measured time: `cargo nextest run` (every test in a process of its own),
# load 7-10 on the 2 cores. Slow is an integration test that took 5 s or more there, or that
# starts chromium or LinuxCNC's simulated machine: 72 of the 152, 2,843 s of their 2,919 s.
# That is the LinuxCNC runs (tests/linuxcnc.rs), the 200-run randomised matching
# (tests/logs.rs), the chromium reports (report, place, ldbb), the calibration sweeps
# (calibrate, calibrate_real, place), determinism over thread counts, the random cells
# (safety), and every test that needs all shipped cells compiled in every dialect (the cache of
# tests/dialects.rs, ~35 s, used by dialects, corners, compensate and linuxcnc). One test over
# 5 s stays fast: the golden NJ-130 program (snapshots, 11 s), the shipped program that must
# stay byte-identical. The unit tests (src/) are all fast by definition (the longest, order's
# local search, took 27 s).
# A new test that takes seconds gets the same attribute.
#
# Why #[ignore] and not a cargo feature or a second test binary: a feature changes the
# library's fingerprint, so each switch between the tiers would rebuild the whole crate (2-3
# min, more than the fast tier itself); a second binary would move tests out of their topic
# files and compile the shared helpers (common, the dialects cache) twice.
test: test-deps
	$(CARGO) test --locked -- --include-ignored

test-fast: test-deps
	$(CARGO) test --locked

fmt:
	$(CARGO) fmt --check

clippy:
	$(CARGO) clippy --all-targets --locked -- -D warnings

doc:
	RUSTDOCFLAGS="-D warnings" $(CARGO) doc --no-deps --locked

# Re-record golden programs after an intended change, then review the diff in git.
snapshots:
	INSTA_UPDATE=always $(CARGO) test --locked --test main snapshots
	rm -f snapshots/*.snap.new
	git diff --stat -- snapshots/

# Throughput of the hot stages and the end-to-end compile (see BENCHMARKS.md); writes
# target/bench.json. The release binary is built first: the bench times it end to end.
bench: build
	$(CARGO) run --release --locked --example bench

# Digital twin: diagnose on a 10-minute, 50 Hz run (30,000 rows).
bench-diagnose:
	$(CARGO) run --release --locked --example bench_diagnose

# Fig. 12: sensitivity of the compiled program vs the ISO 230-4 circle test, 20 random robots.
paper:
	$(CARGO) run --release --locked --example paper

# Pose selection on static readings: 12 simulated NJ-130s read once at the compiler's 35 poses
# and at 35 random poses of the same pool (the paper's premise at equal effort).
pose-selection:
	$(CARGO) run --release --locked --example pose_selection

# What a program buys: 25 simulated NJ-130s calibrated from the compiled program, the ISO
# circle and random poses; true MAP error over the joint space next to the prediction.
calibration:
	$(CARGO) run --release --locked --example calibration

# Measuring without a synchronous joint log: 10 simulated NJ-130s, the
# stop-and-measure program from the bar's own log and the continuous one with a joint log,
# each against its synchronous reference.
stop-and-measure:
	$(CARGO) run --release --locked --example stop_and_measure

# edbbgen against LKH-3 (elkai), OR-tools and Pinocchio on the same instances, in a throwaway
# venv under target/. Not part of `make test` or CI: it downloads the peers from PyPI.
PEERS_VENV := target/peers-venv
bench-peers: build
	test -x $(PEERS_VENV)/bin/python || python3 -m venv $(PEERS_VENV)
	for p in numpy elkai ortools pin; do \
	  $(PEERS_VENV)/bin/pip install -q $$p || echo "bench-peers: $$p failed to install; continuing without it"; \
	done
	$(CARGO) run --release --locked --example bench -- --peers target/peers
	$(PEERS_VENV)/bin/python bench/peers.py target/peers target/bench.json

# Coverage-guided fuzzing of every parser (cargo-fuzz on a nightly toolchain; installed here if
# missing). FUZZ_SECONDS per target; the corpus grows under fuzz/corpus/, crashes land in
# fuzz/artifacts/ (each one becomes a regression case in tests/fuzz.rs). Not part of CI: the
# stable proptest side (tests/fuzz.rs) runs in `make test`.
FUZZ_SECONDS ?= 600
FUZZ_TARGETS := dh urdf mesh cell truth measured_csv gcode template ldbb
fuzz:
	rustup toolchain list | grep -q nightly || rustup toolchain install nightly --profile minimal
	command -v cargo-fuzz >/dev/null || $(CARGO) install cargo-fuzz --locked
	$(CARGO) +nightly fuzz build -O
	for t in $(FUZZ_TARGETS); do \
	  echo "== $$t"; \
	  $(CARGO) +nightly fuzz run -O $$t -- -max_total_time=$(FUZZ_SECONDS) -rss_limit_mb=2048 -timeout=10 2>&1 \
	    | grep -E '^Done|ERROR|SUMMARY|crash-|timeout-|oom-' || exit 1; \
	done

check: fmt clippy test doc

ci: check
