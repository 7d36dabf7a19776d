#!/usr/bin/python3
"""Runs an edbbgen `ngc` program on a headless simulated LinuxCNC machine and records its trace.

    sim.py PROGRAM.ngc --vel V1,..,V6 -o TRACE.csv [--period-us 1000]

The machine is trivkins with X Y Z A B C = joints 1-6 in degrees (X Y Z are LinuxCNC's linear
axes, so their "mm" are degrees here), each axis's maximum velocity from `--vel` (deg/s, the
robot file's joint speeds) and its maximum acceleration from the program's own header line
`(joint accelerations: a1, ..., a6 deg/s^2)`. LinuxCNC's real interpreter, task, trajectory
planner and motion controller run the program; a display-less driver (this file, started by
LinuxCNC as its DISPLAY with --drive) starts it and resumes every M0; HAL's `sampler` records
`joint.N.pos-cmd` every servo period and `halsampler` writes it out. The trace is written as
`t_s,q1_deg,...,q6_deg` (DESIGN.md "Trace"), t = sample number x servo period.

    sim.py ... --wall WALL.csv

also writes `t_s,wall_s`: for each sample of the trace, the wall-clock time since the first, from
HAL's `timedelta` (the time between two runs of the servo thread, on the host's monotonic
clock). On a stock kernel the servo thread is an ordinary thread: a loaded host makes it miss
periods, so the trace's servo time runs slow against the wall clock on which the task times
each dwell (and on which an instrument beside the machine records).

As root, LinuxCNC's uspace rtapi_app refuses to start unless RTAPI_UID names another user and
RTAPI_FIFO_PATH is writable by that user: the run uses `nobody` and a private directory.
Several runs may go at once: each runs in its own IPC namespace (`unshare --ipc`), so their HAL
and NML shared memory never meet.
"""
import os
import re
import shutil
import subprocess
import sys
import tempfile
import time


def header_accelerations(text):
    m = re.search(r"\(joint accelerations: ([^)]*) deg/s\^2\)", text)
    if not m:
        sys.exit("sim.py: the program states no joint accelerations")
    acc = [float(v) for v in m.group(1).split(",")]
    if len(acc) != 6 or min(acc) <= 0:
        sys.exit("sim.py: six positive joint accelerations expected")
    return acc


INI = """[EMC]
MACHINE = edbbgen-sim
DEBUG = 0
VERSION = 1.1

[DISPLAY]
DISPLAY = {driver} --drive {program}

[TASK]
TASK = milltask
CYCLE_TIME = 0.001

[RS274NGC]
PARAMETER_FILE = {dir}/sim.var
FEATURES = 0

[EMCMOT]
EMCMOT = motmod
COMM_TIMEOUT = 1.0
SERVO_PERIOD = {period_ns}

[EMCIO]
EMCIO = io
CYCLE_TIME = 0.100
TOOL_TABLE = {dir}/tool.tbl

[HAL]
HALFILE = {dir}/sim.hal

[TRAJ]
COORDINATES = X Y Z A B C
LINEAR_UNITS = mm
ANGULAR_UNITS = degree
DEFAULT_LINEAR_VELOCITY = 1.0
MAX_LINEAR_VELOCITY = 100000.0
DEFAULT_LINEAR_ACCELERATION = 100000.0
MAX_LINEAR_ACCELERATION = 100000.0
DEFAULT_ANGULAR_VELOCITY = 1.0
MAX_ANGULAR_VELOCITY = 100000.0
NO_FORCE_HOMING = 1
POSITION_FILE = {dir}/position.txt

[KINS]
KINEMATICS = trivkins coordinates=XYZABC
JOINTS = 6
"""

AXIS = """
[AXIS_{name}]
MIN_LIMIT = -100000.0
MAX_LIMIT = 100000.0
MAX_VELOCITY = {vel}
MAX_ACCELERATION = {acc}

[JOINT_{j}]
TYPE = {kind}
HOME = 0.0
MIN_LIMIT = -100000.0
MAX_LIMIT = 100000.0
MAX_VELOCITY = {vel}
MAX_ACCELERATION = {acc}
FERROR = 100000.0
MIN_FERROR = 100000.0
HOME_SEQUENCE = 0
"""

# The sampler FIFO holds 200 s at 1 ms (11 MB): a whole run, startup included, so a halsampler
# starved on a loaded machine (the servo threads run at realtime priority) loses nothing.
HAL = """loadrt [KINS]KINEMATICS
loadrt [EMCMOT]EMCMOT servo_period_nsec=[EMCMOT]SERVO_PERIOD num_joints=[KINS]JOINTS
loadrt sampler cfg=ffffffs depth=200000
loadrt timedelta count=1
addf motion-command-handler servo-thread
addf motion-controller servo-thread
addf timedelta.0 servo-thread
addf sampler.0 servo-thread
net wall timedelta.0.out => sampler.0.pin.6
net estop iocontrol.0.user-enable-out => iocontrol.0.emc-enable-in
"""


def setup(dir, program, vel, acc, period_ns, driver):
    names = "XYZABC"
    ini = INI.format(driver=driver, program=program, dir=dir, period_ns=period_ns)
    for j in range(6):
        ini += AXIS.format(name=names[j], j=j, vel=vel[j], acc=acc[j],
                           kind="LINEAR" if j < 3 else "ANGULAR")
    hal = HAL
    for j in range(6):
        hal += f"net q{j} joint.{j}.motor-pos-cmd => joint.{j}.motor-pos-fb\n"
        hal += f"net p{j} joint.{j}.pos-cmd => sampler.0.pin.{j}\n"
    # halsampler reads the FIFO while the machine runs and ends with it.
    hal += f"loadusr halsampler -c 0 -t {dir}/samples.txt\n"
    with open(f"{dir}/sim.ini", "w") as f:
        f.write(ini)
    with open(f"{dir}/sim.hal", "w") as f:
        f.write(hal)
    with open(f"{dir}/tool.tbl", "w") as f:
        f.write("")
    with open(f"{dir}/sim.var", "w") as f:
        f.write("")


def realtime_servo():
    """Gives this machine's servo thread a real-time priority, as LinuxCNC has on a real-time
    kernel. On a stock kernel uspace runs it as an ordinary thread, at the niceness of the test
    run: on a loaded host it then misses servo periods while the task times each dwell on the
    wall clock, and a 2 s dwell came out as 0.29 s of periods in the trace. Best effort (the
    run's own PID namespace holds only this machine; without the privilege nothing changes)."""
    for pid in os.listdir("/proc"):
        if not pid.isdigit():
            continue
        try:
            tids = os.listdir(f"/proc/{pid}/task")
        except OSError:
            continue
        for tid in tids:
            try:
                with open(f"/proc/{pid}/task/{tid}/comm") as f:
                    if not f.read().startswith("rtapi_app:T#"):
                        continue
                os.sched_setscheduler(int(tid), os.SCHED_FIFO, os.sched_param(10))
            except OSError:
                try:
                    os.setpriority(os.PRIO_PROCESS, int(tid), -20)
                except OSError:
                    pass


def drive(program):
    """LinuxCNC's DISPLAY: run the program, resume every M0, exit when it ends."""
    import linuxcnc
    s, c = linuxcnc.stat(), linuxcnc.command()
    deadline = time.time() + 180  # generous: several machines start at once on a loaded 2-core host
    while True:
        try:
            s.poll()
            break
        except linuxcnc.error:
            if time.time() > deadline:
                sys.exit("sim.py: task did not come up")
            time.sleep(0.1)
    realtime_servo()

    def wait(cond, what, secs=180):
        end = time.time() + secs
        while True:
            s.poll()
            if cond():
                return
            if time.time() > end:
                sys.exit(f"sim.py: timed out waiting for {what}")
            time.sleep(0.01)

    c.state(linuxcnc.STATE_ESTOP_RESET)
    c.state(linuxcnc.STATE_ON)
    wait(lambda: s.task_state == linuxcnc.STATE_ON, "machine on")
    c.mode(linuxcnc.MODE_AUTO)
    wait(lambda: s.task_mode == linuxcnc.MODE_AUTO, "auto mode")
    c.program_open(program)
    c.auto(linuxcnc.AUTO_RUN, 0)
    wait(lambda: s.interp_state != linuxcnc.INTERP_IDLE, "the program to start")
    pauses = 0
    while True:
        s.poll()
        err = linuxcnc.error_channel().poll()
        if err:
            print(f"sim.py: linuxcnc: {err[1]}", file=sys.stderr)
        if s.interp_state == linuxcnc.INTERP_IDLE:
            break
        if s.interp_state == linuxcnc.INTERP_PAUSED or s.paused:
            pauses += 1
            c.auto(linuxcnc.AUTO_RESUME)
            time.sleep(0.05)
        time.sleep(0.005)
    # halsampler may lag far behind on a loaded host (the servo threads run at realtime
    # priority): LinuxCNC's shutdown would kill it with the trace's end still in the FIFO. The
    # machine stands now; wait until halsampler has caught up (a few samples left at most).
    end = time.time() + 600
    while True:
        r = subprocess.run(["halcmd", "getp", "sampler.0.curr-depth"],
                           capture_output=True, text=True)
        if r.returncode == 0 and int(r.stdout.strip() or "0") < 50:
            break
        if time.time() > end:
            sys.exit(f"sim.py: halsampler did not empty the sampler FIFO: {r.stdout}{r.stderr}")
        time.sleep(0.1)
    time.sleep(0.5)
    with open(os.path.join(os.path.dirname(s.ini_filename), "done"), "w") as f:
        f.write(f"{pauses}\n")


def run(program, vel, acc, period_us, opts):
    """One machine runs the program: (its directory, None) when it ran to its end, else the
    reason (LinuxCNC's own print and debug files, whose tails say why)."""
    # Outside /tmp, which the run replaces with a private one.
    dir = tempfile.mkdtemp(prefix="edbb-lcnc-", dir=opts.get("--dir", "/var/tmp"))
    os.chmod(dir, 0o777)
    shutil.copy(program, f"{dir}/program.ngc")
    # The driver too: LinuxCNC starts it inside the private /tmp, where a checkout under /tmp
    # (a clone there, CI's) is hidden ("Can't execute DISPLAY program").
    driver = f"{dir}/sim.py"
    shutil.copy(os.path.abspath(__file__), driver)
    os.chmod(driver, 0o755)
    setup(dir, f"{dir}/program.ngc", vel, acc, period_us * 1000, driver)
    env = dict(os.environ)
    env.pop("DISPLAY", None)
    if os.geteuid() == 0:
        env["RTAPI_UID"] = str(int(opts.get("--uid", "65534")))
        env["RTAPI_FIFO_PATH"] = f"{dir}/rtapi_fifo"
    env["HOME"] = dir
    cmd = ["linuxcnc", f"{dir}/sim.ini"]
    if os.geteuid() == 0 and shutil.which("unshare"):
        # A machine of its own: LinuxCNC's shared memory (IPC namespace), its lock file in
        # /tmp and the processes its scripts find and kill by name (PID namespace), so
        # several runs may go at once.
        cmd = ["unshare", "--ipc", "--pid", "--fork", "--mount-proc", "--mount", "sh", "-c",
               'mount -t tmpfs tmpfs /tmp && exec "$@"', "sh"] + cmd
    r = subprocess.run(cmd, env=env, cwd=dir, stdin=subprocess.DEVNULL,
                       stdout=subprocess.PIPE, stderr=subprocess.STDOUT, timeout=900)
    if os.path.exists(f"{dir}/done"):
        return dir, None
    why = f"exit status {r.returncode}\n" + r.stdout.decode(errors="replace")[-2000:]
    for name in ("linuxcnc_print.txt", "linuxcnc_debug.txt"):
        try:
            with open(f"{dir}/{name}", errors="replace") as f:
                why += f"\n--- {name}:\n" + f.read()[-2000:]
        except OSError:
            pass
    return dir, why


def main():
    args = sys.argv[1:]
    if "--drive" in args:
        # Started by LinuxCNC as its DISPLAY: `sim.py -ini INI --drive PROGRAM`.
        drive(args[args.index("--drive") + 1])
        return
    program = os.path.abspath(args[0])
    opts = dict(zip(args[1::2], args[2::2]))
    vel = [float(v) for v in opts["--vel"].split(",")]
    period_us = int(opts.get("--period-us", "1000"))
    out = opts["-o"]
    with open(program) as f:
        acc = header_accelerations(f.read())
    # LinuxCNC's start-up can fail on a loaded host (five machines start at once beside other
    # tests): a run that does not reach the program's end is tried again on a fresh machine,
    # up to three times, each failure's reason on stderr. A program that cannot run fails all.
    for attempt in range(1, 4):
        dir, why = run(program, vel, acc, period_us, opts)
        if why is None:
            break
        print(f"sim.py: attempt {attempt}: the program did not run to its end:\n{why}",
              file=sys.stderr)
        shutil.rmtree(dir, ignore_errors=True)
    else:
        sys.exit("sim.py: the program did not run to its end in three attempts")
    try:
        period = period_us * 1e-6
        rows, wall, ns = [], [], 0
        with open(f"{dir}/samples.txt") as f:
            for line in f:
                v = line.split()
                if len(v) != 8:
                    continue
                # halsampler numbers the samples: a gap is a FIFO overrun (samples lost).
                # The FIFO overwrites its oldest samples when halsampler falls behind (a loaded
                # machine starves it while the servo threads run at realtime priority): the
                # first sample must be number 0, or the trace's start is gone.
                if not rows and int(v[0]) != 0:
                    sys.exit(f"sim.py: the sampler lost the first {v[0]} samples")
                if rows and int(v[0]) != last + 1:
                    sys.exit(f"sim.py: the sampler lost samples after {last}")
                last = int(v[0])
                t = f"{last * period:.6f}"
                rows.append(t + "," + ",".join(v[1:7]))
                # timedelta's first run has no period before it: it reports 0.
                if rows[1:]:
                    ns += int(v[7])
                wall.append(f"{t},{ns * 1e-9:.6f}")
        with open(out, "w") as f:
            f.write("t_s,q1_deg,q2_deg,q3_deg,q4_deg,q5_deg,q6_deg\n")
            f.write("\n".join(rows) + "\n")
        if "--wall" in opts:
            with open(opts["--wall"], "w") as f:
                f.write("t_s,wall_s\n")
                f.write("\n".join(wall) + "\n")
    finally:
        if "--keep" not in opts:
            shutil.rmtree(dir, ignore_errors=True)


if __name__ == "__main__":
    main()
