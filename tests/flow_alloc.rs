//! `Dis::compute_into` allocates nothing in steady state: counted with a
//! wrapping global allocator, on the thread that runs the computation.

use std::alloc::{GlobalAlloc, Layout, System};
use std::cell::Cell;

use optical_tactile::flow::FlowField;
use optical_tactile::flow::dis::{Dis, DisPreset};

mod support;

thread_local! {
    static COUNT: Cell<usize> = const { Cell::new(0) };
}

/// Counts allocations made by the current thread.
struct Counting;

// The only unsafe code in the crate's tests: forwarding to the system
// allocator is the one way to observe allocations.
#[allow(unsafe_code)]
unsafe impl GlobalAlloc for Counting {
    unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
        let _ = COUNT.try_with(|c| c.set(c.get() + 1));
        // SAFETY: same contract as the caller's.
        unsafe { System.alloc(layout) }
    }
    unsafe fn dealloc(&self, ptr: *mut u8, layout: Layout) {
        // SAFETY: same contract as the caller's.
        unsafe { System.dealloc(ptr, layout) }
    }
}

#[global_allocator]
static GLOBAL: Counting = Counting;

#[test]
fn compute_into_allocates_nothing_in_steady_state() {
    let (w, h) = (320, 240);
    let motion = support::press_motion(w, h, 2.0, 3);
    let (r, c, _) = support::marker_pair(w, h, &motion, 3);
    // One thread: every kernel then runs on this thread, so the
    // thread-local counter sees all of the computation's allocations.
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(1)
        .build()
        .unwrap();
    pool.install(|| {
        for preset in DisPreset::ALL {
            let mut dis = Dis::with_preset(preset);
            let start = COUNT.with(|n| n.get());
            dis.set_reference(&r).unwrap();
            // The counter works: planning does allocate.
            assert!(COUNT.with(|n| n.get()) > start);
            let mut out = FlowField::zeros(w, h);
            dis.compute_into(&c, &mut out).unwrap(); // warm-up sizes buffers
            let before = COUNT.with(|n| n.get());
            dis.compute_into(&c, &mut out).unwrap();
            dis.compute_into(&c, &mut out).unwrap();
            let after = COUNT.with(|n| n.get());
            assert_eq!(
                after - before,
                0,
                "{preset:?} allocated {} times",
                after - before
            );
        }
    });
}
