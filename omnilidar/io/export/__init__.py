"""Export of generated scans and their pseudo-labels to other tools' dataset formats.

One module per target format (``openpcdet``, ``mmdet3d_seg``, ``mmdet3d_det``);
``frames`` gathers and checks what is exported. Nothing is imported here.
"""
