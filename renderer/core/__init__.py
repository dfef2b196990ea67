"""What every part of the tracer passes along: rays and hits (`rays`), rigid transforms (`transforms`),
declared scene parameters (`params`), errors (`errors`), branch-free selection (`blend`) and the allocator
(`memory`)."""
