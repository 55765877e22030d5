//! Once a size is planned, a decomposition allocates nothing: counted with a
//! global allocator that wraps the system one.
#![allow(unsafe_code)] // GlobalAlloc is an unsafe trait; this only counts.

use std::alloc::{GlobalAlloc, Layout, System};
use std::sync::atomic::{AtomicUsize, Ordering};

use ndarray::{Array2, s};
use optical_tactile::hhd::{Decomposition, NaturalHhd};

struct Counting;

static ALLOCS: AtomicUsize = AtomicUsize::new(0);

unsafe impl GlobalAlloc for Counting {
    unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
        ALLOCS.fetch_add(1, Ordering::SeqCst);
        unsafe { System.alloc(layout) }
    }
    unsafe fn dealloc(&self, ptr: *mut u8, layout: Layout) {
        unsafe { System.dealloc(ptr, layout) }
    }
    unsafe fn realloc(&self, ptr: *mut u8, layout: Layout, new_size: usize) -> *mut u8 {
        ALLOCS.fetch_add(1, Ordering::SeqCst);
        unsafe { System.realloc(ptr, layout, new_size) }
    }
}

#[global_allocator]
static GLOBAL: Counting = Counting;

#[test]
fn planned_decompositions_do_not_allocate() {
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
}
