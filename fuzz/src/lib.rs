//! What every fuzz target shares: a counting global allocator, so that a
//! decode allocating more than `decode_bounded`'s bound (32 × the input's
//! length + 2 MiB in one allocation) fails the target as a crash would.

use std::alloc::{GlobalAlloc, Layout, System};
use std::cell::Cell;

struct Counting;

thread_local! {
    static COUNTING: Cell<bool> = const { Cell::new(false) };
    static LARGEST: Cell<usize> = const { Cell::new(0) };
}

fn note(size: usize) {
    if COUNTING.try_with(Cell::get).unwrap_or(false) {
        let _ = LARGEST.try_with(|l| l.set(l.get().max(size)));
    }
}

unsafe impl GlobalAlloc for Counting {
    unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
        note(layout.size());
        unsafe { System.alloc(layout) }
    }
    unsafe fn alloc_zeroed(&self, layout: Layout) -> *mut u8 {
        note(layout.size());
        unsafe { System.alloc_zeroed(layout) }
    }
    unsafe fn dealloc(&self, ptr: *mut u8, layout: Layout) {
        unsafe { System.dealloc(ptr, layout) }
    }
    unsafe fn realloc(&self, ptr: *mut u8, layout: Layout, new_size: usize) -> *mut u8 {
        note(new_size);
        unsafe { System.realloc(ptr, layout, new_size) }
    }
}

#[global_allocator]
static GLOBAL: Counting = Counting;

/// The largest single allocation a decoder may make for `len` bytes.
pub fn bound(len: usize) -> usize {
    2 * formation_record::bounded::ALLOCATION_FACTOR * len + (2 << 20)
}

/// Runs `decode` on `data` (what it returns is dropped inside) and panics
/// if one of its allocations exceeded [`bound`].
pub fn check<R>(data: &[u8], decode: impl FnOnce(&[u8]) -> R) {
    LARGEST.set(0);
    COUNTING.set(true);
    drop(decode(data));
    COUNTING.set(false);
    let largest = LARGEST.get();
    assert!(
        largest <= bound(data.len()),
        "{largest} bytes in one allocation for a {}-byte input (bound {})",
        data.len(),
        bound(data.len())
    );
}
