# Every target CI needs is here; `.ci/run` calls `make ci`.
CARGO ?= cargo
NJ130 := robots/comau_nj130/robot.dh.toml

.PHONY: build run test check fmt clippy doc snapshots bench bench-diagnose paper ci

build:
	$(CARGO) build --release --locked

# The main job: the error-sensitive program for the bundled NJ-130 cell (the paper's fixture).
run: build
	target/release/edbbgen $(NJ130) --fixture 258,1468,708 -o nj130.nc

# The test command the README gives.
test:
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

bench:
	$(CARGO) run --release --locked --example bench

# Digital twin: diagnose on a 10-minute, 50 Hz run (30,000 rows).
bench-diagnose:
	$(CARGO) run --release --locked --example bench_diagnose

# Fig. 12: sensitivity of the compiled program vs the ISO 230-4 circle test, 20 random robots.
paper:
	$(CARGO) run --release --locked --example paper

check: fmt clippy test doc

ci: check
