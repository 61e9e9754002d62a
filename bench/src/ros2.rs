//! `formation bench-net --ros2`: what publishing on ROS 2's wire costs the
//! control loop. The scenario in real time at 1 kHz, alternately with and
//! without `[ros2]` (each agent then also puts odom, cmd_vel,
//! leader_estimate and /tf every step, the leader its odom and /tf): the
//! real-time loop's period error side by side (median of the runs).

use crate::hearing::{network_json, periods_side_by_side, worst_period};
use formation_exit::Error;
use formation_launch::options::LaunchArgs;

/// Runs of each kind; the medians are printed.
const RUNS: usize = 3;

/// `launch(sets, port, out, run)` builds the launch of one run.
pub fn run(
    duration_s: f64,
    port: u16,
    launch: &dyn Fn(&[String], u16, std::path::PathBuf, &str) -> LaunchArgs,
) -> Result<(), Error> {
    let tmp = std::env::temp_dir().join(format!("formation-bench-ros2-{}", std::process::id()));
    let (mut on, mut off) = (Vec::new(), Vec::new());
    for r in 0..RUNS {
        for ros2 in [true, false] {
            eprintln!("bench-net --ros2: run {} of {RUNS}, ROS 2 {} …", r + 1, if ros2 { "on" } else { "off" });
            let sets = vec![
                format!("duration={duration_s}"),
                "timing=realtime".into(),
                "dt=0.001".into(),
                format!("ros2.enabled={ros2}"),
            ];
            let out = tmp.join(format!("run-{r}-{ros2}"));
            let mut l = launch(&sets, port + 10 * (2 * r as u16 + u16::from(ros2)), out.clone(), "bench-ros2");
            l.opts.time_scale = Some(1.0);
            formation_launch::launch::run(&l)?;
            let p = worst_period(&network_json(&out, "the real-time run")?);
            if ros2 {
                on.push(p);
            } else {
                off.push(p);
            }
            let _ = std::fs::remove_dir_all(&out);
        }
    }
    let _ = std::fs::remove_dir_all(&tmp);
    println!("ROS 2 topics: real time at 1 kHz, {duration_s} s, median of {RUNS} runs each");
    periods_side_by_side(("ROS 2 on", &on), ("ROS 2 off", &off));
    Ok(())
}
