//! Index tables read backwards: for each point, the slots of a table that name it.
//!
//! A gather `y[s] = x[table[s]]` has the scatter `∂x[p] += ∂y[s]` as its backward, which on a GPU
//! is a zero-filled buffer and float atomic adds: two launches, and a sum whose order changes
//! from run to run. Where the table is planned on the host (the Point Transformer's hierarchy,
//! design.md §7.5), its inverse costs a pass over it there, and the backward becomes a gather:
//! each point's thread sums the slots that name it, in slot order, and writes once.

/// The inverse of `table` over `points` points, as `[offsets (points + 1) | slots]`: the slots
/// naming point `p` are `slots[offsets[p]..offsets[p + 1]]`, in increasing order. An entry
/// outside `0..points` names no point.
pub(crate) fn readers(table: &[i64], points: usize) -> Vec<i64> {
    let named = |&v: &i64| usize::try_from(v).ok().filter(|&p| p < points);
    let mut offsets = vec![0i64; points + 1];
    for p in table.iter().filter_map(named) {
        offsets[p + 1] += 1;
    }
    for p in 0..points {
        offsets[p + 1] += offsets[p];
    }
    let mut next: Vec<i64> = offsets[..points].to_vec();
    let mut slots = vec![0i64; offsets[points] as usize];
    for (slot, p) in table.iter().enumerate() {
        if let Some(p) = named(p) {
            slots[next[p] as usize] = slot as i64;
            next[p] += 1;
        }
    }
    offsets.into_iter().chain(slots).collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Offsets and slots in order, a point named twice by one row, points named by none, and
    /// entries out of range ignored.
    #[test]
    fn readers_list_the_slots_naming_each_point() {
        let table = [2, 0, 2, -1, 3, 7, 0];
        assert_eq!(
            readers(&table, 4),
            vec![0, 2, 2, 4, 5, /* slots */ 1, 6, 0, 2, 4]
        );
        assert_eq!(readers(&[], 2), vec![0, 0, 0]);
    }
}
