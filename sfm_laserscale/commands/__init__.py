"""One module per command of the command line, each with the same shape: its inputs, options
and result as dataclasses and one ``run(inputs, out_dir, options, overwrite)`` that reads the
inputs, calls the stages and writes the outputs. ``cli.py`` is a thin click layer over them;
the commands hold no maths (the stages do).

:mod:`.scale` (the model's metric scale), :mod:`.detect` (laser spots only), :mod:`.calibrate`
(the rig from target images), :mod:`.apply` (rescale by a known scale), :mod:`.demo` (a
synthetic end-to-end run), :mod:`.simulate` (the paper's synthetic experiments). The command
line contract (options, exit status, outputs) is docs/OUTPUTS.md.
"""
