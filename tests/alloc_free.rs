//! The simulator's step allocates nothing: a counting global allocator in
//! this test binary sees zero allocations over many steps of the paper
//! scenario (on either robot) and of a generated 1000-follower ring.

use std::alloc::{GlobalAlloc, Layout, System};
use std::cell::Cell;
use std::sync::atomic::{AtomicUsize, Ordering};

use formation_scenario::{generate, Scenario};
use formation_sim::{NoRecord, Simulation};

struct Counting;
static ALLOCATIONS: AtomicUsize = AtomicUsize::new(0);

thread_local! {
    /// Only the measuring thread counts: the test harness allocates on its
    /// own threads at any time.
    static COUNTING: Cell<bool> = const { Cell::new(false) };
}

unsafe impl GlobalAlloc for Counting {
    unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
        if COUNTING.try_with(Cell::get).unwrap_or(false) {
            ALLOCATIONS.fetch_add(1, Ordering::Relaxed);
        }
        unsafe { System.alloc(layout) }
    }
    unsafe fn dealloc(&self, ptr: *mut u8, layout: Layout) {
        unsafe { System.dealloc(ptr, layout) }
    }
}

#[global_allocator]
static GLOBAL: Counting = Counting;

fn allocations_in_steps(s: &Scenario, steps: u64) -> usize {
    let mut sim = Simulation::new(s);
    sim.step(&mut NoRecord).unwrap();
    let before = ALLOCATIONS.load(Ordering::Relaxed);
    COUNTING.set(true);
    for _ in 0..steps {
        sim.step(&mut NoRecord).unwrap();
    }
    COUNTING.set(false);
    ALLOCATIONS.load(Ordering::Relaxed) - before
}

#[test]
fn stepping_does_not_allocate() {
    // The counter itself counts: a Vec allocated while counting is seen.
    COUNTING.set(true);
    let v: Vec<u64> = Vec::with_capacity(8);
    COUNTING.set(false);
    drop(v);
    assert_eq!(ALLOCATIONS.load(Ordering::Relaxed), 1, "the counting allocator missed an allocation");

    let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("scenarios/paper.toml");
    let paper = Scenario::load(&path, &[]).unwrap();
    assert_eq!(allocations_in_steps(&paper, 2000), 0, "paper scenario");
    let velocity = Scenario::load(&path, &["robot.model=velocity".to_string()]).unwrap();
    assert_eq!(allocations_in_steps(&velocity, 2000), 0, "paper scenario on velocity-commanded robots");
    let ring = generate::ring_with_chords(1000, 200, 3).unwrap();
    assert_eq!(allocations_in_steps(&ring, 20), 0, "1000-follower ring");
}
