//! Once a size is planned, a decomposition allocates nothing: counted with a
//! global allocator that wraps the system one.
#![allow(unsafe_code)] // GlobalAlloc is an unsafe trait; this only counts.

use std::alloc::{GlobalAlloc, Layout, System};
use std::sync::atomic::{AtomicUsize, Ordering};

use ndarray::{Array2, s};
use optical_tactile::hhd::{Decomposition, DivergentPart, NaturalHhd};

struct Counting;

static ALLOCS: AtomicUsize = AtomicUsize::new(0);

/// Counts one allocation if this thread belongs to the test that is counting.
fn note() {
    let tag = COUNTED.with(|c| c.get());
    if tag != 0 && tag == COUNTING.load(Ordering::SeqCst) {
        ALLOCS.fetch_add(1, Ordering::SeqCst);
    }
}

unsafe impl GlobalAlloc for Counting {
    unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
        note();
        unsafe { System.alloc(layout) }
    }
    unsafe fn dealloc(&self, ptr: *mut u8, layout: Layout) {
        unsafe { System.dealloc(ptr, layout) }
    }
    unsafe fn realloc(&self, ptr: *mut u8, layout: Layout, new_size: usize) -> *mut u8 {
        note();
        unsafe { System.realloc(ptr, layout, new_size) }
    }
}

#[global_allocator]
static GLOBAL: Counting = Counting;

thread_local! {
    /// Which test this thread works for (0: none). Only the threads of the
    /// test that is counting ([`COUNTING`]) are counted: not the test harness
    /// reporting another test meanwhile, nor the other test's pool workers,
    /// which outlive it.
    static COUNTED: std::cell::Cell<u8> = const { std::cell::Cell::new(0) };
}

/// The tag of the test that is counting now (0: none).
static COUNTING: std::sync::atomic::AtomicU8 = std::sync::atomic::AtomicU8::new(0);

/// Tags of the tests.
const PLANNED: u8 = 1;
const SPLIT: u8 = 2;
const DIVERGENT: u8 = 3;

fn count_this_thread(tag: u8) {
    COUNTED.with(|c| c.set(tag));
}

/// The counter is shared: the tests of this file take turns.
static SERIAL: std::sync::Mutex<()> = std::sync::Mutex::new(());

#[test]
fn planned_decompositions_do_not_allocate() {
    let _turn = SERIAL.lock().unwrap_or_else(|e| e.into_inner());
    count_this_thread(PLANNED);
    COUNTING.store(PLANNED, Ordering::SeqCst);
    let big_u = Array2::from_shape_fn((80, 120), |(i, j)| ((i * 7 + j * 3) % 11) as f32 * 0.1);
    let big_v = Array2::from_shape_fn((80, 120), |(i, j)| ((i * 5 + j * 2) % 13) as f32 * 0.1);
    // Two patch sizes, strided windows of a bigger flow.
    let windows = [s![3..63, 10..110], s![20..79;2, 0..120;3]];
    let mut hhd = NaturalHhd::new();
    let mut outs: Vec<Decomposition> = windows
        .iter()
        .map(|w| {
            let (u, v) = (big_u.slice(*w), big_v.slice(*w));
            hhd.decompose(u, v, 1.0, 1.5).unwrap()
        })
        .collect();
    let before = ALLOCS.load(Ordering::SeqCst);
    for _ in 0..3 {
        for (w, out) in windows.iter().zip(outs.iter_mut()) {
            let (u, v) = (big_u.slice(*w), big_v.slice(*w));
            hhd.decompose_into(u, v, 1.0, 1.5, out).unwrap();
        }
    }
    let after = ALLOCS.load(Ordering::SeqCst);
    assert_eq!(after - before, 0, "allocations in planned decompositions");
    // The counter does see allocations.
    let probe = std::hint::black_box(vec![0u8; 64]);
    assert!(ALLOCS.load(Ordering::SeqCst) > after);
    drop(probe);
    COUNTING.store(0, Ordering::SeqCst);
}

#[test]
fn a_torus_split_over_two_threads_does_not_allocate_either() {
    let _turn = SERIAL.lock().unwrap_or_else(|e| e.into_inner());
    count_this_thread(SPLIT);
    COUNTING.store(SPLIT, Ordering::SeqCst);
    // 60x300 pads to 120x600, past PARALLEL_MIN_CELLS: the FFT passes are
    // cut in halves by rayon::join. Run on a pool worker, as the sensor does
    // (a join from outside the pool hands the job over through a queue).
    // The global pool, whose workers never exit: a private pool's would
    // wind down, and allocate, while the next test counts.
    let u = Array2::from_shape_fn((60, 300), |(i, j)| ((i * 7 + j * 3) % 11) as f32 * 0.1);
    let v = Array2::from_shape_fn((60, 300), |(i, j)| ((i * 5 + j * 2) % 13) as f32 * 0.1);
    rayon::ThreadPoolBuilder::new()
        .num_threads(2)
        .start_handler(|_| count_this_thread(SPLIT))
        .build_global()
        .expect("only this test sets up the global pool");
    let ((before, after), ()) = rayon::join(
        || {
            let mut hhd = NaturalHhd::new();
            let mut out = hhd.decompose(u.view(), v.view(), 2.0, 2.0).unwrap();
            let before = ALLOCS.load(Ordering::SeqCst);
            for _ in 0..20 {
                hhd.decompose_into(u.view(), v.view(), 2.0, 2.0, &mut out)
                    .unwrap();
            }
            (before, ALLOCS.load(Ordering::SeqCst))
        },
        || (),
    );
    COUNTING.store(0, Ordering::SeqCst);
    assert_eq!(after - before, 0, "allocations in split decompositions");
}

#[test]
fn planned_divergent_parts_do_not_allocate_whatever_the_sizes() {
    let _turn = SERIAL.lock().unwrap_or_else(|e| e.into_inner());
    count_this_thread(DIVERGENT);
    COUNTING.store(DIVERGENT, Ordering::SeqCst);
    let big_u = Array2::from_shape_fn((80, 120), |(i, j)| ((i * 7 + j * 3) % 11) as f32 * 0.1);
    let big_v = Array2::from_shape_fn((80, 120), |(i, j)| ((i * 5 + j * 2) % 13) as f32 * 0.1);
    // Two patch sizes through one part, as a slot of the extractor sees
    // them from frame to frame: its storage is reshaped, not reallocated.
    let windows = [s![3..63, 10..110], s![20..79;2, 0..120;3]];
    let mut hhd = NaturalHhd::new();
    let mut part = DivergentPart::default();
    for w in &windows {
        let (u, v) = (big_u.slice(*w), big_v.slice(*w));
        hhd.divergent_into(u, v, 2.0, 2.0, &mut part).unwrap();
    }
    let before = ALLOCS.load(Ordering::SeqCst);
    for _ in 0..3 {
        for w in &windows {
            let (u, v) = (big_u.slice(*w), big_v.slice(*w));
            hhd.divergent_into(u, v, 2.0, 2.0, &mut part).unwrap();
        }
    }
    let after = ALLOCS.load(Ordering::SeqCst);
    COUNTING.store(0, Ordering::SeqCst);
    assert_eq!(after - before, 0, "allocations in planned divergent parts");
}
