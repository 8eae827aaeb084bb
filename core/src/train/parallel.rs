//! A tiny deterministic parallel map over scoped threads.
//!
//! Owns the deterministic thread fan-out of the trainer. Must not make results depend on the thread
//! count.

/// `f(workspace, item)` for every item, spread over one contiguous chunk per workspace (one thread
/// each; the first chunk runs on the calling thread). Results come back in item order and each one
/// depends only on its item, so the output does not depend on the number of workspaces. Callers pass
/// at least one workspace (with none, nothing is computed).
pub(crate) fn parallel_map<T, W, R>(
    items: &[T],
    workspaces: &mut [W],
    f: impl Fn(&mut W, &T) -> R + Sync,
) -> Vec<R>
where
    T: Sync,
    W: Send,
    R: Send,
{
    let workers = workspaces.len().min(items.len());
    if workers <= 1 {
        let Some(workspace) = workspaces.first_mut() else {
            return Vec::new();
        };
        return items.iter().map(|item| f(workspace, item)).collect();
    }
    let chunk = items.len().div_ceil(workers);
    let f = &f;
    std::thread::scope(|scope| {
        let mut chunks = items.chunks(chunk).zip(workspaces.iter_mut());
        let Some((first_items, first_workspace)) = chunks.next() else {
            return Vec::new();
        };
        let handles: Vec<_> = chunks
            .map(|(items, workspace)| {
                scope.spawn(move || {
                    items
                        .iter()
                        .map(|item| f(workspace, item))
                        .collect::<Vec<R>>()
                })
            })
            .collect();
        let mut results: Vec<R> = first_items
            .iter()
            .map(|item| f(first_workspace, item))
            .collect();
        for handle in handles {
            match handle.join() {
                Ok(part) => results.extend(part),
                // Re-raise a worker's panic on the caller (there is no other sensible result).
                Err(payload) => std::panic::resume_unwind(payload),
            }
        }
        results
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn results_are_in_order_and_independent_of_the_worker_count() {
        let items: Vec<u64> = (0..23).collect();
        let square_plus_id = |seen: &mut Vec<u64>, x: &u64| {
            seen.push(*x);
            x * x
        };
        let expected: Vec<u64> = items.iter().map(|x| x * x).collect();
        for workers in 1..=5 {
            let mut workspaces = vec![Vec::new(); workers];
            assert_eq!(
                parallel_map(&items, &mut workspaces, square_plus_id),
                expected
            );
            // Every item was handled exactly once, in contiguous chunks.
            let handled: Vec<u64> = workspaces.concat();
            assert_eq!(handled, items);
        }
        assert!(parallel_map(&items, &mut Vec::<()>::new(), |_, x| *x).is_empty());
    }
}
