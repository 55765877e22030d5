//! Steady state: once its buffers have grown, the segmenter allocates nothing
//! per frame (`segment_into` with a reused output list).
//!
//! Counting allocations needs a `GlobalAlloc`, whose trait is `unsafe`: this
//! test binary alone allows `unsafe_code`; the library keeps it denied.
#![allow(unsafe_code)]

use std::alloc::{GlobalAlloc, Layout, System};
use std::cell::Cell;

use optical_tactile::flow::FlowField;
use optical_tactile::segment::{Segmenter, SegmenterConfig, Thresholds};

struct Counting;

thread_local! {
    static COUNT: Cell<usize> = const { Cell::new(0) };
}

// Counts allocations made by the current thread only (the test harness may
// allocate on others).
unsafe impl GlobalAlloc for Counting {
    unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
        COUNT.with(|c| c.set(c.get() + 1));
        unsafe { System.alloc(layout) }
    }
    unsafe fn dealloc(&self, ptr: *mut u8, layout: Layout) {
        unsafe { System.dealloc(ptr, layout) }
    }
    unsafe fn realloc(&self, ptr: *mut u8, layout: Layout, new_size: usize) -> *mut u8 {
        COUNT.with(|c| c.set(c.get() + 1));
        unsafe { System.realloc(ptr, layout, new_size) }
    }
}

#[global_allocator]
static GLOBAL: Counting = Counting;

fn scene(shift: f32) -> FlowField {
    let mut f = FlowField::zeros(480, 270);
    for ((y, x), u) in f.u.indexed_iter_mut() {
        for (cx, cy) in [
            (100.0 + shift, 100.0),
            (300.0, 150.0 - shift),
            (420.0, 60.0),
        ] {
            let r2 = (x as f32 - cx).powi(2) + (y as f32 - cy).powi(2);
            *u += 2.0 * (-r2 / 200.0).exp();
        }
    }
    f
}

#[test]
fn no_allocation_per_frame_in_steady_state() {
    let frames: Vec<FlowField> = (0..4).map(|i| scene(i as f32 * 3.0)).collect();
    for thresholds in [
        Thresholds::MID,
        Thresholds {
            shape: optical_tactile::segment::morphology::Shape::Ellipse,
            ..Thresholds::HIGH
        },
    ] {
        let mut seg = Segmenter::new(SegmenterConfig {
            thresholds,
            margin: 8,
            scale: 4.0,
        })
        .unwrap();
        let mut out = Vec::with_capacity(16);
        for f in &frames {
            seg.segment_into(f, &mut out).unwrap();
        }
        assert!(!out.is_empty());
        let before = COUNT.with(Cell::get);
        for _ in 0..3 {
            for f in &frames {
                seg.segment_into(f, &mut out).unwrap();
            }
        }
        let allocs = COUNT.with(Cell::get) - before;
        assert_eq!(
            allocs, 0,
            "{thresholds:?}: {allocs} allocations in 12 frames"
        );
    }
}
