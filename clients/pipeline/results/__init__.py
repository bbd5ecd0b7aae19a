"""What a reconstruction writes: the output-folder policy, the files and the pictures."""
